"""`--method nerf`: the original NeRF (Mildenhall et al. 2020: the volume rendering integral,
Sec. 4; stratified and hierarchical sampling, Sec. 5.2).

Positional encoding (L = 10 for position, L = 4 for direction, raw input included), an MLP of
`depth` x `width` whose layer `skip_layer` also sees the encoded input (the paper concatenates
it to the fifth layer's activation: skips=[4] in the reference code), density from
position only, colour from a `width` feature + the encoded direction through one `width / 2`
layer. Two such networks: the coarse one is rendered at `n_coarse` stratified samples, the fine
one at those plus `n_fine` samples drawn from the coarse weights by inverse-CDF sampling. The
loss is the sum of both MSEs (Mildenhall et al. 2020, eq. 6).

Empty-space skipping (`occupancy_res > 0`, the CPU default; the paper preset turns it off): the
shared occupancy grid, refreshed from the fine network's density, shrinks every ray's range to the
hull of its occupied cells before the coarse samples are laid out, so the same sample budget lands
on the object; rays that cross no occupied cell are not sent through either network at all (they
see the background: for an unbounded capture a learned environment map, `recon.models.background`).
When the scene has SfM points the grid starts from the cells around them instead of every cell.

Speed on a CPU (lego-200, 2 threads, `bench/results/volume_tuning.md`): the MLP matmuls run in
bf16 under autocast where the hardware has native bf16 (`precision`), 3x the fp32 step rate; the
colour layer applies gamma(d) once per ray instead of once per sample; and the learning rate
starts 10x higher than the paper's, decaying over 8,000 steps (~30 min here).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from recon.cameras import Cameras
from recon.fields.encodings import positional_encoding, positional_encoding_dim
from recon.metrics.image import training_psnr
from recon.models.background import (
    EnvironmentMap,
    check_random_background,
    learns_background,
)
from recon.models.base import (
    MethodSpec,
    Model,
    OptimizerSpec,
    ParamGroup,
    ResolutionPolicy,
    SceneInfo,
    TrainData,
    TrainingBackground,
    register,
)
from recon.models.raymarch import (
    mlp_dtype,
    points_in_box,
    ray_bounds,
    render_image,
    sample_rays,
    scatter_rays,
)
from recon.models.schedules import exp_decay_lr
from recon.options import opt
from recon.volrend import (
    OccupancyGrid,
    contract,
    intervals_from_points,
    merge_points,
    normalize_to_box,
    sample_pdf,
    scene_to_unit_cube,
    spaced_intervals,
    stratified_intervals,
    volume_render,
)
from recon.volrend.occupancy import ray_spans
from recon.volrend.samplers import uniform

# The MLPs see a number of rays rounded up to a multiple of this. With occupancy skipping the
# number of hit rays changes every step, and oneDNN compiles (and caches) one bf16 matmul
# primitive per shape: without buckets every step paid for new primitives and the cache grew the
# process to 5.9 GB. Padding costs at most 63 rays of compute.
RAY_BUCKET = 64
# Renders evaluate this many samples of every live ray at a time before checking which rays have
# become opaque (`NeRFModel._render_terminated`): fewer checks against less wasted work.
TERMINATION_GROUP = 8


@dataclass(frozen=True)
class NeRFConfig:
    """NeRF. Defaults are the CPU "fast" preset (same family, smaller); "paper" is the paper's."""

    pos_bands: int = opt(10, "positional-encoding bands L of the position")
    dir_bands: int = opt(4, "positional-encoding bands L of the view direction")
    depth: int = opt(4, "layers of the position MLP (paper: 8)")
    width: int = opt(128, "width of the position MLP (paper: 256)")
    skip_layer: int = opt(
        2, "0-based layer that receives [h, gamma(x)] (paper: 5, after layer 4's output)"
    )
    n_coarse: int = opt(32, "stratified samples per ray for the coarse network (paper: 64)")
    n_fine: int = opt(64, "extra inverse-CDF samples per ray for the fine network (paper: 128)")
    rays_per_batch: int = opt(1024, "rays per training step (paper: 4096)")
    density_activation: str = opt(
        "softplus", "relu (paper) | softplus (smoother start, as mip-NeRF)"
    )
    lr: float = opt(
        5e-3, "Adam learning rate at step 0 (paper: 5e-4; 10x learns faster on a CPU budget)"
    )
    lr_final: float = opt(5e-5, "learning rate after lr_decay_steps (exponential decay)")
    lr_decay_steps: int = opt(
        8000, "steps of the learning-rate decay: ~30 min here (paper: 250k x 1000 / 500)"
    )
    background: str = opt(
        "auto", "auto (learned for unbounded scenes) | scene (the capture's colour) | learned"
    )
    random_background: str = opt(
        "off",
        "auto (on where the training photos have alpha and the background is the scene's colour) | on | off: train each ray on a random background colour",
    )
    precision: str = opt(
        "auto", "MLP matmuls: auto (bf16 where native: AMX / AVX512-BF16 / CUDA) | bf16 | fp32"
    )
    occupancy_res: int = opt(
        64, "occupancy-grid resolution for empty-space skipping (0 = off, as the paper)"
    )
    occupancy_every: int = opt(16, "steps between occupancy-grid updates")
    occupancy_warmup: int = opt(
        256, "steps with every cell kept occupied (NeRF learns its shape slower than ngp)"
    )
    occupancy_threshold: float = opt(0.01, "cells with opacity EMA below min(this, mean) are empty")
    occupancy_decay: float = opt(0.9, "EMA decay per update of the cell opacities")
    occupancy_seed_dilation: int = opt(
        2, "start from the cells within this many of an SfM point in the box (-1 = all)"
    )
    march_steps: int = opt(
        256, "marching steps along the box diagonal that find each ray's occupied range"
    )
    chunk: int = opt(2048, "rays per chunk when rendering images")
    eps_transmittance: float = opt(
        1e-4,
        "renders stop evaluating a ray's samples once its transmittance is below this (0 = off)",
    )
    default_steps: int = opt(3000, "steps when no stopping rule is given")
    seed: int = opt(0, "seeds ray sampling and sample jitter")


PRESETS = {
    "fast": {},
    "paper": {
        "depth": 8,
        "width": 256,
        "skip_layer": 5,
        "n_coarse": 64,
        "n_fine": 128,
        "rays_per_batch": 4096,
        "density_activation": "relu",
        "lr": 5e-4,
        "lr_decay_steps": 500000,
        "occupancy_res": 0,
        "default_steps": 200000,
        "chunk": 4096,
    },
}


class NeRFMLP(nn.Module):
    """(encoded position, encoded direction) -> (sigma, rgb), the NeRF architecture."""

    def __init__(self, cfg: NeRFConfig):
        super().__init__()
        self.pos_dim = positional_encoding_dim(3, cfg.pos_bands)
        dir_dim = positional_encoding_dim(3, cfg.dir_bands)
        W, self.skip, self.activation = cfg.width, cfg.skip_layer, cfg.density_activation
        dims = [self.pos_dim] + [
            W + (self.pos_dim if i == cfg.skip_layer else 0) for i in range(1, cfg.depth)
        ]
        self.layers = nn.ModuleList(nn.Linear(d, W) for d in dims)
        self.sigma = nn.Linear(W, 1)
        self.feature = nn.Linear(W, W)
        self.color = nn.Sequential(nn.Linear(W + dir_dim, W // 2), nn.ReLU(), nn.Linear(W // 2, 3))

    def geometry(self, x_enc: Tensor) -> tuple[Tensor, Tensor]:
        """sigma (N,) >= 0 (fp32) and the last hidden layer (N, W) from the encoded position."""
        h = x_enc
        for i, layer in enumerate(self.layers):
            if i == self.skip:  # layer `skip` sees [h, gamma(x)] (NeRF's skip connection)
                h = torch.cat([h, x_enc], -1)
            h = F.relu(layer(h))
        raw = self.sigma(h)[:, 0].float()
        sigma = F.relu(raw) if self.activation == "relu" else F.softplus(raw - 1.0)
        return sigma, h

    def colors(self, h: Tensor, d_enc: Tensor) -> Tensor:
        """The colour (N, D, 3) of samples with last hidden layers h (N, W) (`geometry`) seen
        along each of D encoded directions d_enc (D, Dd)."""
        first, W = self.color[0], self.feature.out_features
        per_sample = F.linear(self.feature(h), first.weight[:, :W], first.bias)  # (N, W / 2)
        hidden = per_sample[:, None] + F.linear(d_enc, first.weight[:, W:])[None]
        return torch.sigmoid(self.color[2](F.relu(hidden)).float())

    def forward(self, x_enc: Tensor, d_enc: Tensor) -> tuple[Tensor, Tensor]:
        """x_enc (R*S, P): S samples of each of R rays, ray-major; d_enc (R, D): one encoded
        direction per ray -> sigma (R*S,), rgb (R*S, 3), both fp32.

        The colour layer's input is [feature, gamma(d)]; its matmul is split into the feature
        part (per sample) and the direction part (per ray, broadcast over the S samples), which
        is the same linear map without materialising S copies of gamma(d)."""
        sigma, h = self.geometry(x_enc)
        R = d_enc.shape[0]
        S = x_enc.shape[0] // R if R else 0
        first, W = self.color[0], self.feature.out_features
        per_sample = F.linear(self.feature(h), first.weight[:, :W], first.bias)
        hidden = (
            per_sample.view(R, S, first.out_features)
            + F.linear(d_enc, first.weight[:, W:])[:, None]
        )
        rgb = torch.sigmoid(self.color[2](F.relu(hidden)).float())
        return sigma, rgb.view(-1, 3)


class NeRFModel(Model):
    has_density = True
    has_radiance = True

    def __init__(self, cfg: NeRFConfig, scene: SceneInfo):
        super().__init__()
        if cfg.density_activation not in ("relu", "softplus"):
            raise ValueError(
                f"density_activation must be relu or softplus, got {cfg.density_activation!r}"
            )
        self.cfg, self.scene = cfg, scene
        self.register_buffer("aabb", scene.aabb.clone().float())
        self.register_buffer("background", scene.background.clone().float())
        self.coarse, self.fine = NeRFMLP(cfg), NeRFMLP(cfg)
        self.occupancy = OccupancyGrid(cfg.occupancy_res) if cfg.occupancy_res > 0 else None
        seeds = points_in_box(scene)
        if self.occupancy is not None and seeds is not None and cfg.occupancy_seed_dilation >= 0:
            points_unit = scene_to_unit_cube(seeds.to(self.aabb), self.aabb, scene.unbounded)
            self.occupancy.seed(points_unit, cfg.occupancy_seed_dilation)
        self.environment = (
            EnvironmentMap() if learns_background(cfg.background, scene.unbounded) else None
        )
        check_random_background(cfg.random_background)
        self.random_background = cfg.random_background
        self.dtype = mlp_dtype(self.aabb.device, cfg.precision)
        self.step_size = (self.aabb[1] - self.aabb[0]).norm().item() / cfg.march_steps
        self.generator = torch.Generator().manual_seed(cfg.seed)

    def encode_points(self, points: Tensor) -> Tensor:
        """gamma of world points (N, 3): the box maps to [-1, 1]^3; unbounded scenes contract
        the outside into the radius-2 ball and halve it, so the encoding input stays in [-1, 1]."""
        y = normalize_to_box(points, self.aabb)
        if self.scene.unbounded:
            y = 0.5 * contract(y)
        return positional_encoding(y, self.cfg.pos_bands)

    def _autocast(self):
        """Mixed precision for the MLPs (see `mlp_dtype`); a no-op in fp32."""
        return torch.autocast(
            self.aabb.device.type, dtype=self.dtype, enabled=self.dtype != torch.float32
        )

    def _sigma(self, net: NeRFMLP, x_enc: Tensor) -> Tensor:
        with self._autocast():
            return net.geometry(x_enc.to(self.dtype))[0]

    def density(self, points: Tensor) -> Tensor:
        return self._sigma(self.fine, self.encode_points(points))

    @torch.no_grad()
    def radiance(self, points: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        d_enc = positional_encoding(directions, self.cfg.dir_bands).to(self.dtype)
        with self._autocast():
            sigma, h = self.fine.geometry(self.encode_points(points).to(self.dtype))
            return sigma, self.fine.colors(h, d_enc)

    def sigma_unit(self, x_unit: Tensor) -> Tensor:
        """Fine density (N,) at unit-cube points (the occupancy grid's domain). The encoding input
        of `encode_points` is 2 x_unit - 1 for bounded and unbounded scenes alike."""
        return self._sigma(self.fine, positional_encoding(2.0 * x_unit - 1.0, self.cfg.pos_bands))

    def background_colour(self, directions: Tensor) -> Tensor:
        """What each ray (R, 3) sees behind the volume: the learned environment map (R, 3), or
        the scene's fixed colour (3,) (see `recon.models.background`)."""
        return self.background if self.environment is None else self.environment(directions)

    def _ray_range(self, o: Tensor, d: Tensor, jitter: bool) -> tuple[Tensor, Tensor]:
        """(t_min, t_max) (R,): the scene range, shrunk to the hull of the occupied cells when the
        occupancy grid is on (t_min = t_max: the ray crosses no occupied cell)."""
        t_min, t_max = ray_bounds(self.scene, o, d, self.aabb)
        if self.occupancy is None:
            return t_min, t_max
        u = uniform((o.shape[0],), t_min, self.generator) if jitter else None
        cone = 1 / 256 if self.scene.unbounded else 0.0
        ri, t0, t1 = self.occupancy.march(
            o, d, t_min, t_max, self.aabb, self.scene.unbounded, self.step_size, cone, u
        )
        lo, hi = ray_spans(ri.to(o.device), t0.to(o), t1.to(o), o.shape[0], pad=self.step_size)
        lo, hi = torch.maximum(lo, t_min), torch.minimum(hi, t_max)
        return lo, torch.maximum(hi, lo)

    def _intervals(self, t_min: Tensor, t_max: Tensor, jitter: bool) -> tuple[Tensor, Tensor]:
        """Coarse intervals (R, Nc) x2 tiling [t_min, t_max]."""
        n, g = self.cfg.n_coarse, self.generator
        if self.scene.unbounded:  # linear in disparity: as many samples beyond 2 x near as before
            inv = torch.reciprocal
            return spaced_intervals(t_min, t_max, n, jitter, inv, inv, g)
        return stratified_intervals(t_min, t_max, n, jitter, g)

    def _render_net(
        self,
        net: NeRFMLP,
        o: Tensor,
        d: Tensor,
        t0: Tensor,
        t1: Tensor,
        bg: Tensor | None = None,
    ):
        """One network's render of the intervals (R, S), composited on bg (R, 3) (None: the
        model's background)."""
        R, S = t0.shape
        x = o[:, None] + (0.5 * (t0 + t1))[..., None] * d[:, None]  # (R, S, 3)
        x_enc = self.encode_points(x.reshape(-1, 3)).to(self.dtype)  # cast once: the skip reuses it
        d_enc = positional_encoding(d, self.cfg.dir_bands).to(self.dtype)
        pad = (
            -R % RAY_BUCKET
        )  # zero rays up to a bucket: few distinct matmul shapes (see RAY_BUCKET)
        with self._autocast():
            sigma, rgb = net(F.pad(x_enc, (0, 0, 0, pad * S)), F.pad(d_enc, (0, 0, 0, pad)))
        sigma, rgb = (
            sigma[: R * S],
            rgb[: R * S],
        )  # the padded rows get no gradient: weights see none
        bg = self.background_colour(d) if bg is None else bg
        return volume_render(sigma.view(R, S), rgb.view(R, S, 3), t0, t1, background=bg)

    def _render_terminated(
        self, net: NeRFMLP, o: Tensor, d: Tensor, t0: Tensor, t1: Tensor, colour: bool
    ):
        """`_render_net` for renders (no gradient): the samples are evaluated GROUP at a time
        along the rays, and a ray whose optical depth so far exceeds -ln(eps_transmittance)
        evaluates no more of them (early ray termination, Levoy 1990; as instant-ngp's renderer):
        they would add weights below eps in all. With colour=False only the density runs (the
        coarse pass of a render needs its weights, not its colours: those are left 0)."""
        R, S = t0.shape
        x = o[:, None] + (0.5 * (t0 + t1))[..., None] * d[:, None]  # (R, S, 3)
        d_enc = positional_encoding(d, self.cfg.dir_bands).to(self.dtype)
        sigma, rgb, delta = t0.new_zeros(R, S), t0.new_zeros(R, S, 3), t1 - t0
        depth = t0.new_zeros(R)  # optical depth sum_j sigma_j delta_j over the evaluated samples
        min_depth = -math.log(self.cfg.eps_transmittance)
        for s0 in range(0, S, TERMINATION_GROUP):
            s1 = min(S, s0 + TERMINATION_GROUP)
            alive = (depth <= min_depth).nonzero()[:, 0]
            A, G = alive.numel(), s1 - s0
            if A == 0:
                break
            x_enc = self.encode_points(x[alive, s0:s1].reshape(-1, 3)).to(self.dtype)
            pad = -A % RAY_BUCKET  # few distinct matmul shapes, as `_render_net`
            x_enc = F.pad(x_enc, (0, 0, 0, pad * G))
            with self._autocast():
                if colour:
                    sig, col = net(x_enc, F.pad(d_enc[alive], (0, 0, 0, pad)))
                    rgb[alive, s0:s1] = col[: A * G].view(A, G, 3)
                else:
                    sig = net.geometry(x_enc)[0]
            sig = sig[: A * G].view(A, G)
            sigma[alive, s0:s1] = sig
            depth[alive] += (sig * delta[alive, s0:s1]).sum(-1)
        return volume_render(sigma, rgb, t0, t1, background=self.background_colour(d))

    def _render_hits(
        self,
        o: Tensor,
        d: Tensor,
        t_min: Tensor,
        t_max: Tensor,
        jitter: bool,
        terminate: bool,
        bg: Tensor | None = None,
    ):
        """Coarse render, inverse-CDF fine samples, fine render -> (coarse, fine) VolumeRender.
        terminate: both passes by `_render_terminated` (renders; the coarse colours are then 0).
        bg: (R, 3) per-ray background for training (None: the model's)."""
        t0, t1 = self._intervals(t_min, t_max, jitter)
        if terminate:
            coarse = self._render_terminated(self.coarse, o, d, t0, t1, colour=False)
        else:
            coarse = self._render_net(self.coarse, o, d, t0, t1, bg)
        edges = torch.cat([t0, t1[:, -1:]], -1)
        t_fine = sample_pdf(edges, coarse.weights, self.cfg.n_fine, jitter, self.generator)
        t_all = merge_points(0.5 * (t0 + t1), t_fine)
        f0, f1 = intervals_from_points(t_all, t_min, t_max)
        if terminate:
            return coarse, self._render_terminated(self.fine, o, d, f0, f1, colour=True)
        return coarse, self._render_net(self.fine, o, d, f0, f1, bg)

    def _render_rays(
        self,
        o: Tensor,
        d: Tensor,
        jitter: bool,
        terminate: bool = False,
        background: Tensor | None = None,
    ) -> tuple[dict, dict]:
        """Both passes on the rays with a non-empty range only -> (coarse, fine) dicts of rgb (R, 3),
        depth (R,) (expected t), acc (R,) and hit (R,) bool; rays that miss get the background, 0, 0.
        terminate: early ray termination (`_render_terminated`; renders only).
        background: (R, 3) colours to composite on (training on random backgrounds; None: the
        model's own)."""
        t_min, t_max = self._ray_range(o, d, jitter)
        is_hit = t_max > t_min
        hit = is_hit.nonzero()[:, 0]
        if hit.numel() == o.shape[0]:
            passes = self._render_hits(o, d, t_min, t_max, jitter, terminate, background)
        else:
            bg = None if background is None else background[hit]
            passes = self._render_hits(
                o[hit], d[hit], t_min[hit], t_max[hit], jitter, terminate, bg
            )
        R = o.shape[0]
        missed_bg = background  # the missed rays see the background: given, environment or fixed
        if missed_bg is None and self.environment is not None and hit.numel() < R:
            missed_bg = self.environment(d)
        return tuple(
            {
                "rgb": self._fill_missed(
                    scatter_rays(p.rgb, hit, R, self.background), is_hit, missed_bg
                ),
                "depth": scatter_rays(p.depth, hit, R, None),
                "acc": scatter_rays(p.acc, hit, R, None),
                "hit": is_hit,
            }
            for p in passes
        )

    @staticmethod
    def _fill_missed(rgb: Tensor, is_hit: Tensor, background: Tensor | None) -> Tensor:
        """rgb (R, 3) with the rows of missed rays replaced by background (R, 3) (None: as is)."""
        return rgb if background is None else torch.where(is_hit[:, None], rgb, background)

    def _update_occupancy(self, step: int) -> None:
        cfg = self.cfg
        if self.occupancy is not None and step % cfg.occupancy_every == 0:
            self.occupancy.update(
                self.sigma_unit,
                self.step_size,
                step < cfg.occupancy_warmup,
                cfg.occupancy_decay,
                cfg.occupancy_threshold,
                generator=self.generator,
            )

    @property
    def learns_background(self) -> bool:
        return self.environment is not None

    def step_pixels(self, data: TrainData) -> int:
        return self.cfg.rays_per_batch

    def optimizers(self) -> dict[str, OptimizerSpec]:
        cfg = self.cfg
        schedule = lambda step: exp_decay_lr(step, cfg.lr, cfg.lr_final, cfg.lr_decay_steps)
        fused = self.aabb.device.type == "cpu" or None
        group = ParamGroup("all", list(self.parameters()), schedule)
        return {"main": OptimizerSpec([group], fused=fused)}

    def before_step(self, data: TrainData, step: int) -> None:
        self._update_occupancy(step)

    def training_loss(
        self, data: TrainData, step: int, background: TrainingBackground
    ) -> tuple[Tensor, dict]:
        cfg = self.cfg
        batch = sample_rays(data, cfg.rays_per_batch, self.generator)
        target, colours = background.targets(batch, self.generator)
        coarse, fine = self._render_rays(
            batch["origins"], batch["directions"], jitter=True, background=colours
        )
        mse_c = torch.mean((coarse["rgb"] - target) ** 2)
        mse_f = torch.mean((fine["rgb"] - target) ** 2)
        loss = mse_c + mse_f  # without gradient when no ray crossed an occupied cell
        hit_fraction = fine["hit"].float().mean()
        out = {  # 0-d tensors: read by the loop when it logs (no host sync a step)
            "loss": loss.detach(),
            "psnr": training_psnr(mse_f),
            "psnr_coarse": training_psnr(mse_c),
            "samples_per_ray": (cfg.n_coarse * 2 + cfg.n_fine) * hit_fraction,
        }
        if self.occupancy is not None:
            out["occupied"] = self.occupancy.occupancy_fraction()
        return loss, out

    @torch.no_grad()
    def render(self, camera: Cameras) -> dict[str, Tensor]:
        terminate = self.cfg.eps_transmittance > 0

        def rays_fn(o: Tensor, d: Tensor):
            _, fine = self._render_rays(o, d, jitter=False, terminate=terminate)
            return fine["rgb"], fine["depth"], fine["acc"]

        return render_image(rays_fn, camera.to(self.aabb.device), self.cfg.chunk)

    def load_state_dict(self, state: dict, strict: bool = True):
        """A run saved before nerf had an occupancy grid (no `occupancy.*` entries) or a learned
        background (no `environment.*` entries) was trained and must render without one."""
        if self.occupancy is not None and "occupancy.occupied" not in state:
            self.occupancy = None
        if self.environment is not None and not any(k.startswith("environment.") for k in state):
            self.environment = None
        return super().load_state_dict(state, strict)

    def training_state(self) -> dict:
        return {"generator": self.generator.get_state()}

    def load_training_state(self, state: dict) -> None:
        self.generator.set_state(state["generator"])


def build(config: NeRFConfig, scene: SceneInfo) -> NeRFModel:
    return NeRFModel(config, scene)


# about 3.3k rays/s (1,024-ray batches at 3.2 steps/s on lego-200, 2 threads); one pass over the pixels.
# The throughput probe's first steps, same machine: 197 ms, between lego-200's 174 ms and fox's
# 228 ms (both benchmark scenes, so either sits inside the prior's tolerance).
RESOLUTION = ResolutionPolicy(
    pixels_per_s=3.3e3,
    pixels_per_step=1024,
    min_epochs=1.0,
    max_side=800,
    probe_pixels_per_s=5.2e3,
)
SPEC = register(
    MethodSpec(
        name="nerf", config_cls=NeRFConfig, build=build, presets=PRESETS, resolution=RESOLUTION
    )
)
