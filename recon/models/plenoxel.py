"""Plenoxels (Fridovich-Keil et al. 2022, "Plenoxels: Radiance Fields without Neural Networks"): a sparse voxel grid of
density + spherical-harmonic colour, trilinear interpolation, NO neural network, a total
variation regulariser, coarse-to-fine upsampling and pruning of empty voxels.

Rendered by the shared core: occupancy-grid marching (empty-space skipping), early ray
termination, and `volrend.volume_render` for the quadrature.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numba
import torch
import torch.nn.functional as F
from torch import Tensor

from recon import devices
from recon.cameras import Cameras, camera_rays
from recon.fields.sh import C0, eval_sh, num_sh_bases, sh_basis
from recon.fields.voxels import SparseVoxelGrid
from recon.io.packed import (
    bits_indices,
    deflate,
    dequantize_int8,
    inflate,
    mask_bits,
    quantize_int8,
)
from recon.metrics.image import training_psnr
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
from recon.models.plenoxel_bake import bake_lattice, lattice_points, vertices_in_cells
from recon.models.plenoxel_march import (
    Lattice,
    march_lattice_terminated,
    render_lattice,
    vertex_logits,
)
from recon.models.raymarch import batch_pixels, render_image, sample_rays
from recon.models.registry import load_model
from recon.models.schedules import exp_decay_lr
from recon.options import opt
from recon.volrend import (
    OccupancyGrid,
    ray_aabb_intersect,
    scene_to_unit_cube,
    surface_depth,
    terminated_mask,
    volume_render,
)
from recon.volrend.march_kernels import tile_order

# The finest lattice sized to the training photos (`finest_lattice`): a multiple of this many
# vertices, within these bounds. The bound above is the size used before the rule (measured to
# fit a 10-minute CPU run); finer lattices (the Plenoxels paper's 512^3: `--preset paper`) hold
# 4x the vertices per doubling of the surface's resolution and were not measured to pay here.
LATTICE_MULTIPLE, LATTICE_MIN, LATTICE_MAX = 32, 64, 256


def pixel_footprint(cameras: Cameras, center: Tensor) -> float:
    """How wide one pixel is at the scene: the median over the C cameras of (distance from the
    camera centre to `center` (3,)) / focal length in pixels, in scene units.
    Example: a camera 4.03 from the centre with f = 277.9 px (Blender lego at 200 px) -> 0.0145."""
    centers = cameras.world_from_cam[:, :3, 3].double()
    distance = (centers - center.double().to(centers.device)).norm(dim=-1)
    return float((distance / cameras.K[:, 0, 0].double()).median())


def finest_lattice(side: float, footprint: float, unbounded: bool) -> int:
    """The finest lattice size for a scene box of `side` seen by pixels `footprint` wide there:
    about one voxel of the box per pixel (the box spans the whole lattice, or its middle half
    when unbounded: `scene_to_unit_cube`), rounded to the nearest multiple of LATTICE_MULTIPLE,
    within [LATTICE_MIN, LATTICE_MAX]. Finer voxels than the photos resolve only add parameters
    for the total variation to smooth.
    (bench/results/volume_lean_fast.md: the rule's 192^3 against 256^3 on lego-200.)
    Example: lego-200 (recon's box 0.588, pixels 0.003165 wide) -> 185.8 -> 192; side 3,
    footprint 0.0145 -> 206.9 -> 192, unbounded 413.8 -> 416 -> 256."""
    across = side / footprint / (0.5 if unbounded else 1.0)
    size = math.floor(across / LATTICE_MULTIPLE + 0.5) * LATTICE_MULTIPLE
    return min(max(size, LATTICE_MIN), LATTICE_MAX)


def lattice_schedule(resolutions: tuple, finest: int) -> tuple:
    """The coarse-to-fine sizes: `resolutions` with a last 0 replaced by `finest`, and coarser
    sizes not below it dropped (as given while `finest` is 0: not decided yet).
    Example: (32, 64, 128, 0), 96 -> (32, 64, 96)."""
    if not resolutions or resolutions[-1] != 0 or finest <= 0:
        return tuple(resolutions)
    return tuple(r for r in resolutions[:-1] if r < finest) + (finest,)


@dataclass(frozen=True)
class PlenoxelConfig:
    resolutions: tuple = opt(
        (32, 64, 128, 0),
        "coarse-to-fine lattice sizes; a last 0 is sized to the training photos (`finest_lattice`)",
    )
    upsample_steps: tuple = opt(
        (150, 500, 1500), "steps at which the grid moves to the next resolution"
    )
    sh_degree: int = opt(2, "spherical-harmonic degree of the colour")
    rays_per_batch: int = opt(4096, "rays of the first training step")
    samples_per_batch: int = opt(
        1 << 18, "target samples per step: the ray batch adapts (0 = fixed rays)"
    )
    max_rays_per_batch: int = opt(16384, "upper bound of the adaptive ray batch")
    step_voxels: float = opt(0.5, "marching step, in voxels of the current lattice")
    lr_density: float = opt(0.1, "Adam learning rate of density (in per-voxel optical units)")
    lr_sh: float = opt(0.02, "Adam learning rate of SH coefficients")
    lr_decay_steps: int = opt(
        5000, "learning rates decay by 10x over this many steps (exponentially)"
    )
    tv_density: float = opt(1e-3, "total-variation weight on density")
    tv_sh: float = opt(1e-3, "total-variation weight on SH coefficients")
    tv_fraction: float = opt(0.02, "fraction of voxels per step that the TV term samples")
    prune_density: float = opt(
        0.05, "voxels whose 3x3x3 neighbourhood stays below this density are pruned"
    )
    occupancy_every: int = opt(16, "occupancy-grid update interval (steps)")
    occupancy_res: int = opt(64, "occupancy-grid resolution")
    cone_angle: float = opt(0.0, ">0 grows steps with distance (used for unbounded scenes)")
    eps_transmittance: float = opt(1e-4, "early ray termination threshold")
    finish_weight: float = opt(
        0.001,
        "when training stops, keep only vertices within one voxel of a vertex whose blending weight on some training ray reaches this (0 = keep all)",
    )
    upsample_prune_unseen: bool = opt(
        True,
        "right after each upsampling, prune what no training ray sees (as finish_weight does at the end): the finer lattice's optimizer state and steps hold only that",
    )
    finish_ray_stride: int = opt(
        2, "the final pruning traces every N-th pixel of each row and column of the views"
    )
    chunk: int = opt(16384, "rays per chunk when rendering images")
    bake_from: str = opt(
        "",
        "a trained model.pt (ngp, nerf) to start from: its field baked into the finest lattice at the first step, then trained on (`recon train --bake-from RUN`)",
    )
    bake_directions: int = opt(32, "view directions per vertex the baked colour's SH fit samples")
    bake_voxel_pixels: float = opt(
        1.5,
        "a bake sizes its lattice (a last 0 of resolutions) to voxels this many training pixels wide (plenoxel's own: 1): it is there to render fast",
    )
    default_steps: int = opt(4000, "steps when no stopping rule is given")


class PlenoxelModel(Model):
    has_density = True
    has_point_colors = True

    def __init__(self, cfg: PlenoxelConfig, scene: SceneInfo):
        super().__init__()
        self.cfg, self.scene = cfg, scene
        self.register_buffer("aabb", scene.aabb.clone())
        self.register_buffer("background", scene.background.clone())
        self.register_buffer("level", torch.zeros((), dtype=torch.long))
        # the size a last 0 of cfg.resolutions stands for, fixed at the first step (0 = not yet)
        self.register_buffer("finest", torch.zeros((), dtype=torch.long))
        sizes = cfg.resolutions
        if not sizes or sizes[0] <= 0 or any(r <= 0 for r in sizes[1:-1]) or sizes[-1] < 0:
            raise ValueError(
                "plenoxel resolutions: positive sizes, coarse to fine; only the last of two or "
                f"more may be 0 (sized to the training photos), got {cfg.resolutions}"
            )
        k = num_sh_bases(cfg.sh_degree)
        self.grid = SparseVoxelGrid(
            cfg.resolutions[0], {"density": 1, "sh": 3 * k}, {"density": 0.1}
        )
        self.occupancy = OccupancyGrid(cfg.occupancy_res)
        self.generator = torch.Generator().manual_seed(0)
        self.n_rays = cfg.rays_per_batch  # adapted after every step to hit samples_per_batch
        self._live: Tensor | None = None  # `live_cells`, computed on demand
        self._points: Tensor | None = None  # `_vertex_points`, likewise
        self._samples = 0  # the last step's samples (the next batch's size follows them)

    # ---- field ---------------------------------------------------------------------------
    @property
    def res(self) -> int:
        return self.grid.res

    def to_unit(self, x: Tensor) -> Tensor:
        return scene_to_unit_cube(x, self.aabb, self.scene.unbounded)

    def _box_side(self) -> float:
        """The scene box's longest side, read from the device once (`devices.host_value`)."""
        return devices.host_value(self, "side", self.aabb, lambda a: float((a[1] - a[0]).max()))

    def _level(self) -> int:
        """The current lattice's index in `lattice_sizes` (the `level` buffer, read once)."""
        return devices.host_value(self, "level", self.level, int)

    def _density_scale(self, res: int | None = None) -> float:
        """sigma = relu(d) * res / box side: d = 1 gives optical thickness ~1 per voxel (res:
        the lattice's, by default the current one)."""
        return (res or self.res) / self._box_side() * (0.5 if self.scene.unbounded else 1.0)

    def _sigma_unit(self, x_unit: Tensor) -> Tensor:
        d = self.grid.query(x_unit, ["density"])["density"][:, 0]
        return F.relu(d) * self._density_scale()

    def density(self, points: Tensor) -> Tensor:
        with torch.no_grad():
            return torch.cat([self._sigma_unit(self.to_unit(p)) for p in points.split(1 << 18)])

    def point_colors(self, points: Tensor) -> Tensor:
        """View-independent (degree-0 SH) colour at normalized points (N, 3) -> (N, 3), for meshes."""
        with torch.no_grad():
            out = []
            for p in points.split(1 << 18):
                sh = self.grid.query(self.to_unit(p), ["sh"])["sh"].view(
                    -1, 3, num_sh_bases(self.cfg.sh_degree)
                )
                out.append(torch.sigmoid(sh[:, :, 0] * C0))
            return torch.cat(out)

    def _rgb_sigma(self, x: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        v = self.grid.query(self.to_unit(x))
        sigma = F.relu(v["density"][:, 0]) * self._density_scale()
        coeffs = v["sh"].view(-1, 3, num_sh_bases(self.cfg.sh_degree)).transpose(1, 2)
        rgb = torch.sigmoid(eval_sh(self.cfg.sh_degree, coeffs, dirs))
        return rgb, sigma

    # ---- rays ----------------------------------------------------------------------------
    def _step_t(self) -> float:
        return self.cfg.step_voxels * self._box_side() / self.res

    def _ray_range(self, origins: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor, float]:
        """(t_min, t_max, cone angle) of each ray (R,): the scene box (bounded) or [near, far]."""
        R = origins.shape[0]
        if self.scene.unbounded:
            t_min = torch.full((R,), self.scene.near, device=origins.device)
            t_max = torch.full((R,), self.scene.far, device=origins.device)
            return t_min, t_max, self.cfg.cone_angle or 1.0 / 256
        t_min, t_max, _ = ray_aabb_intersect(origins, dirs, self.aabb)
        t_min = t_min.clamp_min(self.scene.near)
        if self.cfg.cone_angle > 0:
            return t_min, t_max, self.cfg.cone_angle
        return (*self._within_occupied(origins, dirs, t_min, t_max), 0.0)

    def _within_occupied(self, origins: Tensor, dirs: Tensor, t_min: Tensor, t_max: Tensor):
        """[t_min, t_max] (R,) of a bounded scene's rays (steps of `_step_t` from t_min, no
        cone) shrunk to the box around the occupied cells, by whole steps: the march's interval
        k of the shrunk range is interval k + n of the full one, n the steps that end before the
        ray enters that box, so every sample in an occupied cell stays the same (up to rounding),
        and none is marched outside the box (a ray that misses it marches nothing)."""
        box = self.occupancy.occupied_box()
        if box is None:
            return t_min, t_min
        box = self.aabb[0] + box.to(self.aabb) * (self.aabb[1] - self.aabb[0])
        enter, leave, hit = ray_aabb_intersect(origins, dirs, box)
        step = self._step_t()
        n = (torch.floor((enter - t_min) / step) - 1).clamp_min(0)
        start = torch.where(hit, t_min + n * step, t_min)
        end = torch.where(hit, torch.minimum(t_max, leave + step), t_min)
        return start, torch.maximum(end, start)

    @torch.no_grad()
    def kept_samples(self, origins: Tensor, dirs: Tensor, u: Tensor | None):
        """The samples a render keeps: occupied, sigma > 0 and T >= eps (early termination),
        packed (ray_indices, t_starts, t_ends). One numba pass on the CPU
        (`plenoxel_march.march_lattice_terminated`), else `_march_then_terminate`."""
        t_min, t_max, cone = self._ray_range(origins, dirs)
        if not devices.uses_cpu_kernels(origins):
            return self._march_then_terminate(origins, dirs, t_min, t_max, cone, u)
        live = None if u is not None else self.live_cells()  # jittered: a training step
        return march_lattice_terminated(origins, dirs, t_min, t_max, u, self._lattice(cone, live))

    def _lattice(self, cone: float, live: Tensor | None) -> Lattice:
        """The model's grids as the one-pass kernels read them (`plenoxel_march.Lattice`)."""
        coarse, coarse_res = self.occupancy.coarse(math.gcd(self.occupancy.resolution, 4))
        return Lattice(
            self.occupancy.occupied, self.occupancy.resolution, coarse, coarse_res, live, self.aabb,
            self.scene.unbounded, self._step_t(), cone, self.grid.links,
            self.grid.data["density"][:, 0], self.res, self._density_scale(),
            self.cfg.eps_transmittance,
        )  # fmt: skip

    @torch.no_grad()
    def live_cells(self) -> Tensor:
        """((res - 1)^3,) bool: the lattice cells with a vertex of positive density, the only
        ones where sigma > 0 (cell (i, j, k) at i + (res - 1) (j + (res - 1) k)). Kept until
        the density changes: every method that changes it calls `_density_changed`."""
        if self._live is None:
            r, density = self.res, self.grid.data["density"].detach()[:, 0]
            positive = torch.zeros(r**3, dtype=torch.bool, device=density.device)
            positive[self.grid.coords[density > 0]] = True
            v = positive.view(r, r, r)  # (k, j, i)
            live = torch.zeros((r - 1,) * 3, dtype=torch.bool, device=density.device)
            for dk in (0, 1):
                for dj in (0, 1):
                    for di in (0, 1):
                        live |= v[dk : r - 1 + dk, dj : r - 1 + dj, di : r - 1 + di]
            self._live = live.reshape(-1)
        return self._live

    def _density_changed(self) -> None:
        self._live = self._points = None

    @torch.no_grad()
    def _march_then_terminate(self, origins, dirs, t_min, t_max, cone, u):
        """`kept_samples` in two stages: march every occupied sample, evaluate the density of
        all of them, then drop those with sigma = 0 or behind T < eps (`terminated_mask`)."""
        ray_idx, t0, t1 = self.occupancy.march(
            origins, dirs, t_min, t_max, self.aabb, self.scene.unbounded, self._step_t(), cone, u
        )
        if ray_idx.numel():
            mids = 0.5 * (t0 + t1)
            sig = self._sigma_unit(self.to_unit(origins[ray_idx] + mids[:, None] * dirs[ray_idx]))
            keep = terminated_mask(sig, t0, t1, ray_idx, self.cfg.eps_transmittance) & (sig > 0)
            ray_idx, t0, t1 = devices.masked(keep, ray_idx, t0, t1)
        return ray_idx, t0, t1

    def render_rays(
        self, origins: Tensor, dirs: Tensor, jitter: bool, background: Tensor | None = None
    ) -> dict[str, Tensor]:
        """Rays (R, 3) composited on `background` (R, 3) (None: the model's colour)."""
        R = origins.shape[0]
        g = self.generator
        u = torch.rand(R, generator=g, device=g.device).to(origins.device) if jitter else None
        ray_idx, t0, t1 = self.kept_samples(origins, dirs, u)
        mids = 0.5 * (t0 + t1)
        x = origins[ray_idx] + mids[:, None] * dirs[ray_idx]
        rgb, sigma = self._rgb_sigma(x, dirs[ray_idx])
        bg = self.background if background is None else background
        out = volume_render(sigma, rgb, t0, t1, ray_idx, R, bg)
        return {
            "rgb": out.rgb,
            "acc": out.acc,
            "depth": out.depth,
            "samples": ray_idx.numel(),
            "points": x,
            "weights": out.weights,
        }

    @torch.no_grad()
    def vertex_weights(self, origins: Tensor, dirs: Tensor) -> Tensor:
        """For each data row (M,): the largest share a ray of these (R, 3) takes from it, the
        sample's blending weight w_i = T_i alpha_i times the vertex's trilinear weight there."""
        links = self.grid.links
        best = torch.zeros(self.grid.num_rows, dtype=torch.float32, device=links.device)
        for o, d in zip(origins.split(self.cfg.chunk), dirs.split(self.cfg.chunk)):
            out = self.render_rays(o, d, jitter=False)
            if not len(out["points"]):
                continue
            rows, w = self.grid.corners(self.to_unit(out["points"]))  # numba on the CPU only
            share = (out["weights"].float()[:, None] * w.float()).reshape(-1)
            rows = rows.reshape(-1)
            linked = rows >= 0
            best.scatter_reduce_(0, rows[linked], share[linked], "amax")
        return best

    @torch.no_grad()
    def finish(self, data: TrainData) -> dict[str, float]:
        """When training stops: `prune_unseen` (finish_weight 0: nothing)."""
        if self.cfg.finish_weight <= 0:
            return {}
        before = self.grid.num_rows
        self.prune_unseen(data)
        return {"finish_rows_before": float(before), "finish_rows_after": float(self.grid.num_rows)}

    @torch.no_grad()
    def prune_unseen(self, data: TrainData) -> None:
        """Prune by visibility (Fridovich-Keil et al. 2022 prune by the largest weight a voxel
        takes on the training rays): keep the vertices within one voxel (the trilinear
        footprint) of one whose `vertex_weights` over every finish_ray_stride-th pixel of the
        training views reaches finish_weight. Vertices no ray sees are the inside of solid
        objects and the space behind what the cameras see."""
        s = max(1, self.cfg.finish_ray_stride)
        C, H, W, _ = data.images.shape
        pixels = torch.arange(data.num_pixels, device=data.images.device)
        pixels = pixels.reshape(C, H, W)[:, ::s, ::s].reshape(-1)
        best = None
        for part in pixels.split(1 << 18):
            rays = data.rays_at(part)
            w = self.vertex_weights(rays["origins"], rays["directions"])
            best = w if best is None else torch.maximum(best, w)
        self._prune_neighbourhood((best >= self.cfg.finish_weight).float(), 0.0)

    # ---- training ------------------------------------------------------------------------
    def optimizers(self) -> dict[str, OptimizerSpec]:
        # dense fused Adam: pruning keeps the grid small, and one fused pass beats coalescing
        # sparse gradients with many repeated rows (measured: SparseAdam spent 70 % of a step
        # there). The grid's rows change as it is pruned and upsampled: a fresh Adam each time.
        cfg = self.cfg
        groups = [
            ParamGroup(
                name,
                [self.grid.data[name]],
                lambda step, base=base: exp_decay_lr(step, base, 0.1 * base, cfg.lr_decay_steps),
            )
            for name, base in (("density", cfg.lr_density), ("sh", cfg.lr_sh))
        ]
        fused = self.aabb.device.type == "cpu" or None
        return {"main": OptimizerSpec(groups, eps=1e-15, fused=fused)}

    @torch.no_grad()
    def _tv_step(self) -> Tensor:
        """The total-variation term w mean_(pairs, channels) (p_a - p_b)^2 over the +x/+y/+z
        neighbour pairs of a random tv_fraction of the rows (Fridovich-Keil et al. 2022, eq. 4):
        its gradient +-2 w (p_a - p_b) / (P C) is added to each data row's .grad in place (no
        dense (M, C) gradient per term, as autograd through index_select would allocate).
        Returns the term's value, a 0-d float64 tensor on the grid's device (no host sync)."""
        M, gen = self.grid.num_rows, self.generator
        k = max(1, int(self.cfg.tv_fraction * M))
        rows = torch.randint(0, M, (k,), generator=gen, device=gen.device)
        rows = rows.to(self.grid.links.device)
        a, b = self.grid.neighbour_pairs(rows)
        loss = torch.zeros((), dtype=torch.float64, device=self.grid.links.device)
        if a.numel() == 0:
            return loss
        for name, w in (("density", self.cfg.tv_density), ("sh", self.cfg.tv_sh)):
            p = self.grid.data[name]
            diff = p.index_select(0, a) - p.index_select(0, b)
            loss = loss + w * diff.pow(2).mean().double()
            if p.grad is None:
                p.grad = torch.zeros_like(p)
            g = diff * (2 * w / diff.numel())
            p.grad.index_add_(0, a, g)  # index_add: deterministic on multi-threaded CPUs
            p.grad.index_add_(0, b, -g)
        return loss

    def lattice_sizes(self, data: TrainData | None = None) -> tuple:
        """The run's coarse-to-fine lattice sizes (`lattice_schedule`); a last 0 of
        cfg.resolutions is sized by `finest_lattice` from the training cameras `data` the first
        time they are given (a bake's voxels bake_voxel_pixels pixels wide), and kept (saved
        with the model)."""
        finest = devices.host_value(self, "finest", self.finest, int)
        if self.cfg.resolutions[-1] == 0 and finest == 0 and data is not None:
            side, footprint = self._box_and_pixel(data)
            if self.cfg.bake_from:
                footprint *= self.cfg.bake_voxel_pixels
            finest = finest_lattice(side, footprint, self.scene.unbounded)
            self.finest.fill_(finest)
        return lattice_schedule(self.cfg.resolutions, finest)

    def _box_and_pixel(self, data: TrainData) -> tuple[float, float]:
        """The scene box's side and `pixel_footprint` of the training cameras at its centre."""
        return self._box_side(), pixel_footprint(data.cameras, self.aabb.mean(0))

    def plan_note(self, data: TrainData) -> str | None:
        sizes = self.lattice_sizes(data)
        if self.cfg.bake_from:
            return (
                f"plenoxel lattice {sizes[-1]}^3 from the first step (voxels about "
                f"{self.cfg.bake_voxel_pixels:g} pixels wide, to render fast): "
                f"{self.cfg.bake_from} baked into it, then trained on"
            )
        if self.cfg.resolutions[-1] != 0:
            return f"plenoxel lattice {' -> '.join(map(str, sizes))} (as configured)"
        side, footprint = self._box_and_pixel(data)
        return (
            f"plenoxel lattice {' -> '.join(map(str, sizes))}: the finest sized to the training "
            f"photos (a pixel is {footprint:.4g} wide at the scene, the box {side:.3g}: "
            f"about a voxel a pixel; `--set resolutions=...` to choose)"
        )

    def _maybe_upsample(self, step: int, data: TrainData) -> None:
        lvl = self._level()
        sizes = self.lattice_sizes(data)
        if (
            lvl + 1 < len(sizes)
            and lvl < len(self.cfg.upsample_steps)
            and step >= self.cfg.upsample_steps[lvl]
        ):
            self.prune()
            new_res = sizes[lvl + 1]
            scale = (
                new_res / self.res
            )  # keep optical thickness per unit length: d scales with 1/res
            self.grid.upsample(new_res, lambda occ: occ)
            self.grid.data["density"].data /= scale
            self.level.fill_(lvl + 1)
            self._density_changed()
            if self.cfg.upsample_prune_unseen and self.cfg.finish_weight > 0:
                self.prune_unseen(data)  # before the finer lattice's optimizer state exists

    @torch.no_grad()
    def prune(self) -> None:
        """Drop vertices whose 3x3x3 neighbourhood has density below `prune_density`."""
        density = F.relu(self.grid.data["density"].detach()[:, 0])
        self._prune_neighbourhood(density, self.cfg.prune_density)

    @torch.no_grad()
    def _prune_neighbourhood(self, value: Tensor, threshold: float) -> None:
        """Keep the rows whose 3x3x3 vertex neighbourhood holds a `value` (M,) above
        `threshold` (unlinked vertices count as 0); at least 8 rows stay."""
        dense = torch.zeros(self.res**3, device=value.device, dtype=value.dtype)
        dense[self.grid.coords] = value
        near = F.max_pool3d(dense.view(1, 1, *(self.res,) * 3), 3, stride=1, padding=1)
        keep = near.reshape(-1)[self.grid.coords] > threshold
        if int(keep.sum()) >= 8:
            self.grid.prune(keep)  # new rows: the trainer's optimizer starts afresh
            self._density_changed()

    @torch.no_grad()
    def bake(self, data: TrainData) -> None:
        """Start from the trained field of `cfg.bake_from` (`plenoxel_bake.bake_lattice`) on
        the finest lattice sized for `data`, its occupancy grid refreshed from the baked
        density and the vertices no training ray sees pruned (`prune_unseen`)."""
        source = load_model(Path(self.cfg.bake_from), self.scene, self.aabb.device)
        if not source.has_radiance:
            raise ValueError(f"{self.cfg.bake_from}: its method has no radiance field to bake")
        sizes = self.lattice_sizes(data)
        self.level.fill_(len(sizes) - 1)
        res, occupancy = sizes[-1], getattr(source, "occupancy", None)
        candidates = None
        if occupancy is not None:
            candidates = vertices_in_cells(occupancy.occupied.cpu(), occupancy.resolution, res)
        flat, density, sh = bake_lattice(
            source, res, self.aabb, self.scene.unbounded, self.cfg.sh_degree,
            self.cfg.bake_directions, self._density_scale(res), self.cfg.prune_density,
            candidates,
        )  # fmt: skip
        dev = self.aabb.device
        self.grid.set_rows(flat.to(dev), {"density": density.to(dev), "sh": sh.to(dev)}, res)
        self._density_changed()
        self.occupancy.occupied.fill_(True)  # every cell evaluated, then kept as the density says
        self._update_occupancy(warmup=False)
        if self.cfg.finish_weight > 0:
            self.prune_unseen(data)

    def _update_occupancy(self, warmup: bool) -> None:
        cell = self._box_side() / self.cfg.occupancy_res
        self.occupancy.update(self._sigma_unit, cell, warmup=warmup, generator=self.generator)

    def step_pixels(self, data: TrainData) -> int:
        c = self.cfg
        return batch_pixels(
            c.samples_per_batch, PlenoxelConfig.samples_per_batch, RAYS_PER_STEP, self.n_rays
        )

    def before_step(self, data: TrainData, step: int) -> None:
        if step == 0 and self.cfg.bake_from:
            self.bake(data)
        self._maybe_upsample(step, data)
        if step % self.cfg.occupancy_every == 0:
            self._update_occupancy(warmup=step < 32 and not self.cfg.bake_from)

    def training_loss(
        self, data: TrainData, step: int, background: TrainingBackground
    ) -> tuple[Tensor, dict]:
        n_rays = self.n_rays
        batch = sample_rays(data, n_rays, self.generator)
        target, colours = background.targets(batch, self.generator)
        out = self.render_rays(batch["origins"], batch["directions"], True, colours)
        mse = F.mse_loss(out["rgb"], target)
        self._samples = out["samples"]
        return mse, {  # tensors where a float would sync: the loop reads them when it logs
            "loss": mse.detach(),  # + the total variation, after the backward pass
            "psnr": training_psnr(mse),
            "samples_per_ray": out["samples"] / n_rays,
            "rays": n_rays,
            "voxels": self.grid.num_rows,
        }

    def after_backward(self, data: TrainData, step: int, stats: dict) -> None:
        stats["loss"] = stats["loss"] + self._tv_step().float()

    def after_step(self, data, step, optimizers, stats) -> None:
        self._density_changed()
        n_rays = self.n_rays
        if self.cfg.samples_per_batch > 0:  # Instant-NGP: a fixed sample budget, not fixed rays
            wanted = self.cfg.samples_per_batch * n_rays / max(self._samples, 1)
            self.n_rays = int(
                min(max(wanted, n_rays / 2, 256), 2 * n_rays, self.cfg.max_rays_per_batch)
            )

    @torch.no_grad()
    def render(self, camera: Cameras) -> dict[str, Tensor]:
        """Camera 0's image: on the CPU one numba pass per ray (`plenoxel_march.render_lattice`,
        no sample ever stored), elsewhere `render_rays` chunk by chunk; the same pixels."""
        if not devices.uses_cpu_kernels(self.aabb):
            return render_image(self._render_chunk, camera, self.cfg.chunk)
        origins, dirs, z_per_t = camera_rays(camera, 0)
        H, W = z_per_t.shape
        o, d = origins.reshape(-1, 3).float(), dirs.reshape(-1, 3).float()
        # bounded: the colour of each vertex as seen from the camera centre (`vertex_logits`)
        centre = None if self.scene.unbounded else camera.centers[0].float()
        rgb, t, acc = self._render_fused(o, d, tile_order(H, W, numba.get_num_threads()), centre)
        depth = surface_depth(t, acc) * z_per_t.reshape(-1).to(t)
        return {"rgb": rgb.reshape(H, W, 3), "depth": depth.reshape(H, W), "acc": acc.reshape(H, W)}

    def _render_chunk(self, origins: Tensor, directions: Tensor):
        out = self.render_rays(origins, directions, jitter=False)
        return out["rgb"], out["depth"], out["acc"]

    def _render_fused(
        self,
        origins: Tensor,
        dirs: Tensor,
        order: Tensor | None = None,
        centre: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """(rgb (R, 3), expected t (R,), acc (R,)) of CPU rays, as `render_rays` gives them
        (order: `render_lattice`'s); with the camera centre (3,) of a bounded scene's rays, the
        colour is evaluated per vertex as seen from it (`plenoxel_march.vertex_logits`)."""
        t_min, t_max, cone = self._ray_range(origins, dirs)
        lattice = self._lattice(cone, self.live_cells())
        sh = self.grid.data["sh"].detach()
        if centre is None:
            basis, logits = sh_basis(self.cfg.sh_degree, dirs), None
        else:  # no SH along the rays
            basis = dirs.new_empty(dirs.shape[0], 0)
            logits = vertex_logits(self._vertex_points(), centre, sh)
        return render_lattice(
            origins, dirs, t_min, t_max, basis, sh, self.background, lattice, order, logits
        )

    def _vertex_points(self) -> Tensor:
        """(M, 3) the scene point of each row's lattice vertex (a bounded scene's), kept until
        the rows change (`_density_changed`, as `live_cells`)."""
        if self._points is None:
            unit = lattice_points(self.grid.coords, self.res).to(self.aabb)
            self._points = self.aabb[0] + unit * (self.aabb[1] - self.aabb[0])
        return self._points

    # ---- state ---------------------------------------------------------------------------
    def file_state(self) -> dict:
        """model.pt, small: the lattice's vertices as a deflated bitmask of res^3 bits instead of
        the dense `links` table and `coords` (rows in ascending vertex order), density in
        float16 and the SH coefficients in int8 with one scale per coefficient (`io.packed`;
        error <= half a step: renders within ~5e-3, lego-200 PSNR -0.001 dB), both deflated."""
        state = dict(self.state_dict())
        for key in ("grid.links", "grid.coords", "grid.data.density", "grid.data.sh"):
            del state[key]
        coords, order = torch.sort(self.grid.coords)
        q, scale = quantize_int8(self.grid.data["sh"].detach()[order])
        state.update(
            {
                "grid.res": torch.tensor(self.res),
                "grid.vertex_bits": deflate(mask_bits(coords, self.res**3)),
                "grid.density_f16": deflate(self.grid.data["density"].detach()[order].half()),
                "grid.sh_int8": deflate(q),
                "grid.sh_scale": scale,
            }
        )
        return state

    def _unpack_file_state(self, state: dict) -> tuple[Tensor, dict[str, Tensor], int]:
        """(coords, {name: values}, res) of the lattice in any saved form: `state_dict()`
        (checkpoints), `file_state()`, or the earlier file form (int32 coords, float16 SH)."""
        if "grid.vertex_bits" in state:
            res = int(state.pop("grid.res"))
            bits = inflate(state.pop("grid.vertex_bits"), torch.uint8, (-1,))
            coords = bits_indices(bits, res**3)
            M, K = len(coords), self.grid.data["sh"].shape[1]
            density = inflate(state.pop("grid.density_f16"), torch.float16, (M, 1)).float()
            q = inflate(state.pop("grid.sh_int8"), torch.int8, (M, K))
            sh = dequantize_int8(q, state.pop("grid.sh_scale"))
            return coords, {"density": density, "sh": sh}, res
        if "grid.res" in state:
            res = int(state.pop("grid.res"))
        else:
            res = round(state["grid.links"].numel() ** (1 / 3))
        values = {n: state.pop(f"grid.data.{n}").float() for n in self.grid.data}
        return state.pop("grid.coords").long(), values, res

    def load_state_dict(self, state: dict, strict: bool = True):
        """Grids change size during training: resize to the saved shapes first. Reads
        `state_dict()` and `file_state()` (see `_unpack_file_state`)."""
        state = dict(state)
        state.setdefault("finest", torch.zeros((), dtype=torch.long))  # saved before it existed
        coords, values, res = self._unpack_file_state(state)
        device = self.grid.links.device  # a checkpoint is read onto the CPU: keep the model's
        values = {name: v.to(device) for name, v in values.items()}
        self.grid.set_rows(coords.to(device), values, res)
        self._density_changed()
        state.update({"grid.coords": self.grid.coords, "grid.links": self.grid.links})
        state.update({f"grid.data.{n}": v for n, v in values.items()})
        return super().load_state_dict(state, strict)

    def training_state(self) -> dict:
        return {"generator": self.generator.get_state(), "n_rays": self.n_rays}

    def load_training_state(self, state: dict) -> None:
        self.generator.set_state(state["generator"])
        self.n_rays = int(state["n_rays"])

    def stats(self) -> dict[str, float]:
        return {
            "parameters": sum(p.numel() for p in self.grid.data.values()),
            "voxels": self.grid.num_rows,
            "resolution": self.res,
            "finest_resolution": self.lattice_sizes()[-1],
            "occupied_fraction": float(self.occupancy.occupancy_fraction()),
        }


RAYS_PER_STEP = 12000  # a step of the default sample target (`step_pixels`)
register(
    MethodSpec(
        name="plenoxel",
        config_cls=PlenoxelConfig,
        build=PlenoxelModel,
        presets={
            "fast": {},
            "paper": {
                "resolutions": (128, 256, 512),
                "upsample_steps": (2000, 5000),
                "rays_per_batch": 5000,
                "samples_per_batch": 0,
                "default_steps": 12800,
            },
            # SH degree 1 (12 instead of 27 SH floats a vertex): half the memory and the file,
            # more steps, a little less view dependence (bench/results/volume_lean_fast.md)
            "lean": {"sh_degree": 1},
        },
        # about 40k rays/s (adaptive batches up to 16k rays at 2.85 steps/s on lego-200, 2 threads);
        # the throughput probe's first steps, same machine: 36 ms, between lego-200's 29 ms and
        # fox's 46 ms (both benchmark scenes, so either sits inside the prior's tolerance)
        starts_from_fields=True,
        resolution=ResolutionPolicy(
            pixels_per_s=40e3,
            pixels_per_step=RAYS_PER_STEP,
            min_epochs=2.0,
            max_side=800,
            probe_pixels_per_s=330e3,
        ),
    )
)
