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

from recon.fields.sh import num_sh_bases, sh_basis

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
