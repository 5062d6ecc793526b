"""What a volume model composites behind its samples (shared by nerf and ngp).

A synthetic capture was composited on a known colour, and that colour is the right background.
A real photo has none: whatever a ray sees beyond the last sample (or the whole pixel, when the
ray crosses only empty occupancy cells) is scenery too far away to resolve. NeRF++ (Zhang et al.
2020, Sec. 4) models the outside of the unit sphere by an inverted-sphere parameterisation
(x / r, 1 / r); at its limit 1 / r -> 0 the outer field depends on the direction alone. We keep
only that limit: an environment map c_bg(d) = sigmoid(MLP(Y(d))), Y the real spherical
harmonics of degree 3, learnt with the scene. It is composited with the remaining
transmittance, C = sum_i w_i c_i + (1 - sum_i w_i) c_bg(d), so it fills exactly what the
volume leaves open.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from recon.fields.hashgrid import HashGrid
from recon.fields.sh import num_sh_bases, sh_basis
from recon.models.raymarch import mlp, trunc_exp
from recon.volrend import scene_to_unit_cube, spaced_intervals, volume_render

BACKGROUNDS = ("auto", "scene", "learned")
RANDOM_BACKGROUNDS = ("auto", "on", "off")


def learns_background(mode: str, unbounded: bool) -> bool:
    """mode: "scene" (the capture's fixed colour), "learned" (an environment map), or "auto"
    (learned for an unbounded capture, whose photos have no background colour)."""
    if mode not in BACKGROUNDS:
        raise ValueError(f"background must be one of {', '.join(BACKGROUNDS)}, got {mode!r}")
    return mode == "learned" or (mode == "auto" and unbounded)


def check_random_background(mode: str) -> None:
    if mode not in RANDOM_BACKGROUNDS:
        raise ValueError(f"random_background must be auto, on or off, got {mode!r}")


def trains_on_random_background(mode: str, has_alpha: bool, learned: bool) -> bool:
    """Whether training rays are composited on a random colour each (the target moved onto it
    by `recomposite`), as Instant-NGP trains synthetic scenes (Mueller et al. 2022):
    on a fixed background, haze of the background's own colour costs nothing, so a model keeps
    it; on random colours it costs. Needs the photos' alpha and a fixed background colour.
    mode: "on" (an error without alpha, or with a learned environment), "off", or "auto" (on
    where the photos have alpha and the background is the scene's colour)."""
    check_random_background(mode)
    if mode == "on" and (not has_alpha or learned):
        raise ValueError(
            "random_background=on needs training photos with alpha and the scene's background"
        )
    return mode == "on" or (mode == "auto" and has_alpha and not learned)


class EnvironmentMap(nn.Module):
    """c_bg(d) (R, 3) in (0, 1) for unit directions d (R, 3): SH degree `degree` -> one hidden
    ReLU layer of `width` -> sigmoid. Starts as the uniform grey sigmoid(0) = 0.5."""

    def __init__(self, degree: int = 3, width: int = 32):
        super().__init__()
        self.degree = degree
        self.net = nn.Sequential(
            nn.Linear(num_sh_bases(degree), width), nn.ReLU(), nn.Linear(width, 3)
        )
        nn.init.zeros_(self.net[2].weight)
        nn.init.zeros_(self.net[2].bias)

    def forward(self, directions: Tensor) -> Tensor:
        return torch.sigmoid(self.net(sh_basis(self.degree, directions)))


class OuterVolume(nn.Module):
    """What a bounded model sees behind its box: NeRF++'s outer field (Zhang et al. 2020, Sec. 4),
    here a small hash grid over mip-NeRF 360's contraction of the space around the box (Barron
    et al. 2022, eq. 10) instead of the inverted sphere, composited on an `EnvironmentMap`.

    Each ray is sampled from where it leaves the box (a ray that misses the box: from its point
    closest to the box's centre, so nothing is modelled between a camera and the object) to
    `far`, `n_samples` intervals linear in disparity. forward -> the colour (R, 3) the ray sees
    there, the background the inner model composites on: C = C_in + T_in C_out."""

    def __init__(
        self,
        aabb: Tensor,
        near: float,
        far: float,
        n_samples: int = 32,
        n_levels: int = 8,
        log2_table_size: int = 15,
        n_max: int = 256,
        hidden: int = 32,
        sh_degree: int = 2,
        geo_features: int = 7,
    ):
        super().__init__()
        self.register_buffer("aabb", aabb.clone().float())
        self.near, self.far, self.n_samples, self.sh_degree = near, far, n_samples, sh_degree
        self.grid = HashGrid(n_levels, 2, log2_table_size, 16, n_max)
        self.density_mlp = mlp(self.grid.out_dim, hidden, 1, 1 + geo_features)
        self.color_mlp = mlp(geo_features + num_sh_bases(sh_degree), hidden, 1, 3)
        self.environment = EnvironmentMap()

    def start(self, origins: Tensor, directions: Tensor, t_exit: Tensor, hit: Tensor) -> Tensor:
        """Where each ray's outer samples begin (R,): its box exit t_exit where it hits the
        box, else the t of its closest approach to the box's centre (at least `near`)."""
        centre = self.aabb.mean(0)
        closest = ((centre - origins) * directions).sum(-1)
        return torch.where(hit, t_exit, closest).clamp_min(self.near)

    def forward(
        self,
        origins: Tensor,
        directions: Tensor,
        t_start: Tensor,
        jitter: bool,
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """t_start (R,) > 0: where each ray's samples begin (`start`)."""
        R, S = origins.shape[0], self.n_samples
        far = torch.maximum(t_start * 1.0001, torch.full_like(t_start, self.far))
        inv = torch.reciprocal
        t0, t1 = spaced_intervals(t_start, far, S, jitter, inv, inv, generator)  # (R, S)
        x = origins[:, None] + (0.5 * (t0 + t1))[..., None] * directions[:, None]
        h = self.density_mlp(self.grid(scene_to_unit_cube(x.reshape(-1, 3), self.aabb, True)))
        dir_enc = sh_basis(self.sh_degree, directions)
        rgb = torch.sigmoid(
            self.color_mlp(torch.cat([h[:, 1:], dir_enc.repeat_interleave(S, 0)], -1))
        )
        sigma = trunc_exp(h[:, 0]).view(R, S)
        env = self.environment(directions)
        return volume_render(sigma, rgb.view(R, S, 3), t0, t1, background=env).rgb
