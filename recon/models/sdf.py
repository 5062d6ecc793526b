"""`--method sdf`: a signed distance field rendered as a volume (VolSDF, Yariv et al. 2021) on
a multiresolution hash grid (as NeuS2, Wang et al. 2023): the zero level set of the field IS the
surface, and its gradient the surface normal.

The field (`recon.fields.sdf.SDFField`) maps points of the scene box, scaled isotropically into
[-1, 1]^3, to a signed distance f (box half-size units) and a geometry feature; it starts as a
sphere (geometric initialisation, Atzmon & Lipman 2020). The density is VolSDF's Laplace CDF of
the distance (Yariv et al. 2021, eq. 2-3) with a learned scale beta,

    sigma(x) = Psi_beta(-f(x)) / beta     (per box half-size; per scene unit: / R),

so training, early termination and the occupancy grid are those of every volume method
(`recon.volrend`): samples marched through the occupied cells, a gradient-free density pre-pass
to drop what lies behind T < eps (`march_terminated`), then the field with gradients on the
survivors. The colour MLP reads the geometry feature, the gradient grad f (the normal, as IDR,
Yariv et al. 2020, eq. 4 conditions the radiance on it) and the spherical-harmonic encoding of
the view direction. The loss is the colour MSE plus the eikonal term of Gropp et al. 2020
(eq. 2), lambda E(||grad f|| - 1)^2, on the rendered samples and on points drawn uniformly in
the box, with lambda = 0.01: NeuS's 0.1 (Wang et al. 2021, Sec. 3.3) weighs it against an L1
colour loss, whose gradient is ~10x the MSE's at a few percent of error. grad f is exact (the
chain rule through the MLP and the hash grid's analytic Jacobian, `recon.fields.sdf`).

An unbounded capture keeps the field in the scene box and learns what lies beyond it as an
environment map of the view direction (`recon.models.background`), composited behind. With
`outer_volume=on` what lies behind the box is a volume instead (`OuterVolume`: NeRF++'s outer
field on a contracted hash grid, then the environment map): a real backdrop at a finite
distance, such as the board and cables behind the walnut ring, is not a function of the
direction alone.

Where the training photos have alpha (a synthetic capture), two options say that a transparent
pixel's ray must stay empty, which a fixed white background alone does not (an SDF may close
the surface anywhere a view sees white: on sample_data a skirt below the plate's rim): NeuS's
mask term (Wang et al. 2021, Sec. 3.3), the binary cross-entropy between each ray's opacity and
its pixel's alpha (`mask_loss`, `mask_weight`), and training each ray on a random background
colour with its target moved onto it (`recomposite`, as Instant-NGP trains synthetic scenes;
`random_background`). Both are off by default: each raised the mesh's precision but lost more
recall and held-out PSNR than it gained, and the lower eikonal weight gives the plain run the
precision they were for (`bench/results/sdf_alpha.md`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor, nn

from recon.cameras import Cameras
from recon.fields.sdf import SDFField, eikonal_loss, sdf_and_gradient
from recon.fields.sh import num_sh_bases, sh_basis
from recon.metrics.image import training_psnr
from recon.models.background import (
    EnvironmentMap,
    OuterVolume,
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
    batch_pixels,
    mlp,
    points_in_box,
    ray_bounds,
    render_image,
    sample_rays,
)
from recon.models.schedules import (
    exp_decay_lr,
    fit_schedules,
    refit_schedules,
    schedule_state,
)
from recon.options import opt
from recon.volrend import OccupancyGrid, scene_to_unit_cube, volume_render
from recon.volrend.occupancy import MarchFn, march_terminated
from recon.volrend.samplers import uniform
from recon.volrend.sdf_density import volsdf_density


def mask_loss(acc: Tensor, alpha: Tensor, eps: float = 1e-3) -> Tensor:
    """Binary cross-entropy between the rays' opacities acc (N,) and the pixels' alpha (N,)
    (NeuS, Wang et al. 2021, eq. 8's mask term), acc clamped to [eps, 1 - eps].
    Example: acc 0.9 against alpha 1 -> -log 0.9 = 0.10536."""
    a = acc.clamp(eps, 1 - eps)
    return -(alpha * torch.log(a) + (1 - alpha) * torch.log1p(-a)).mean()


@dataclass(frozen=True)
class SDFConfig:
    """A hash-grid SDF with VolSDF density. Defaults are sized for a 2-thread CPU."""

    n_levels: int = opt(16, "hash-grid levels L")
    n_features: int = opt(2, "features per level F")
    log2_table_size: int = opt(17, "log2 of the hash table size T per level")
    n_min: int = opt(16, "coarsest grid resolution")
    n_max: int = opt(1024, "finest grid resolution")
    width: int = opt(64, "hidden width of the SDF MLP")
    n_hidden: int = opt(2, "hidden layers of the SDF MLP")
    geo_features: int = opt(15, "geometry-feature channels passed to the colour MLP")
    color_width: int = opt(64, "hidden width of the colour MLP")
    color_hidden: int = opt(2, "hidden layers of the colour MLP")
    sh_degree: int = opt(3, "SH degree of the view-direction encoding")
    init_radius: float = opt(
        0.5, "radius of the initial sphere, in half-sizes of the box's SHORTEST side"
    )
    beta_init: float = opt(0.1, "initial VolSDF scale beta, in box half-sizes")
    beta_min_steps: float = opt(
        0.25, "beta never falls below this many marching steps (a thinner shell than the samples)"
    )
    levels_start: int = opt(
        16, "coarse-to-fine: hash levels active at step 0 (Neuralangelo, Li et al. 2023, Sec. 3.2)"
    )
    levels_steps: int = opt(2000, "coarse-to-fine: steps until every level is active")
    eikonal_weight: float = opt(
        0.01,
        "lambda of the eikonal term, against the colour MSE (NeuS's 0.1 is against an L1 colour loss, whose gradient is ~10x the MSE's at these errors; 0.1 here over-smooths: bench/results/sdf_eikonal)",
    )
    eikonal_points: int = opt(2048, "points drawn uniformly in the box each step for it")
    points_weight: float = opt(
        1.0,
        "weight of the mean |f| at multi-view-stereo surface points (`recon mvs`), when the "
        "training data has them (Geo-Neus, Fu et al. 2022, Sec. 3.2; 0 = off)",
    )
    points_per_step: int = opt(4096, "surface points drawn each step for that term")
    rays_per_batch: int = opt(1024, "rays of the first training step")
    samples_per_batch: int = opt(
        1 << 15, "target rendered samples per step: the ray batch adapts (0 = fixed)"
    )
    march_steps: int = opt(
        256,
        "marching steps along the scene box diagonal (512: 2.4x fewer rays a second, which a time budget does not win back)",
    )
    max_samples_per_ray: int = opt(1024, "at most this many marched samples per ray (0 = no cap)")
    background: str = opt(
        "auto", "auto (learned for unbounded scenes) | scene (the capture's colour) | learned"
    )
    outer_volume: str = opt(
        "off",
        "on: model what lies behind the box (a real backdrop) with a small hash-grid field over the contracted space, on an environment map (NeRF++'s outer field) | off",
    )
    outer_n_max: int = opt(256, "finest resolution of the outer volume's hash grid")
    random_background: str = opt(
        "off",
        "auto (on where the training photos have alpha and the background is the scene's colour) | on | off: train each ray on a random background colour",
    )
    mask_weight: float = opt(
        0.0,
        "where the training photos have alpha: weight of the binary cross-entropy between each ray's opacity and the pixel's alpha (NeuS's mask loss, which uses 0.1; 0 = off)",
    )
    occupancy_res: int = opt(64, "occupancy grid resolution")
    occupancy_every: int = opt(16, "steps between occupancy-grid updates")
    occupancy_warmup: int = opt(256, "steps during which every cell is kept occupied")
    occupancy_threshold: float = opt(0.01, "cells with opacity EMA below min(this, mean) are empty")
    occupancy_decay: float = opt(0.95, "EMA decay per update of the cell opacities")
    eps_transmittance: float = opt(1e-4, "early ray termination threshold")
    lr: float = opt(1e-2, "Adam learning rate (grid and MLPs)")
    lr_final: float = opt(5e-4, "learning rate reached after lr_decay_steps (exponential decay)")
    lr_decay_steps: int = opt(5000, "steps of the learning-rate decay")
    lr_beta: float = opt(
        2e-2, "learning rate of log beta (a CPU run of a few thousand steps must sharpen fast)"
    )
    schedule_steps: int = opt(
        0,
        "the run's planned length (recon train sets it from the budget): a longer lr decay is fitted into it (0 = as configured)",
    )
    chunk: int = opt(4096, "rays per chunk when rendering images")
    default_steps: int = opt(3000, "steps when no stopping rule is given")
    seed: int = opt(0, "seeds the ray batches, jitter and eikonal points")


PRESETS = {"fast": {}, "paper": {"n_max": 2048, "log2_table_size": 19, "lr_decay_steps": 20000}}
SCHEDULE_FRACTIONS = {"lr_decay_steps": 1.0, "levels_steps": 0.5}
# What a budgeted run re-plans mid-run from its measured step rate (`replan`): the hash levels'
# schedule, not the learning-rate decay, which stays as fitted to the planned run. Re-planned
# to the measured rate, the decay ended with the run and lowered the held-out PSNR: a lower
# learning rate late in a short run starves the field (ngp does not fit its decay either).
REPLAN_FRACTIONS = {"levels_steps": 0.5}
# The termination pre-pass evaluates this many samples of every ray first (`march_terminated`;
# the kept samples are the same whatever it is). An SDF's shell is a few samples thick, so 16
# wastes less behind the surface than ngp's 32: on a trained lego-200 sdf, 29.7 k densities
# evaluated a step instead of 39.9 k for the same 21.4 k kept; a step 250 -> 233 ms, a 200 px
# view 622 -> 515 ms, the same loss to the bit (8 evaluates 26.8 k but is no faster).
TERMINATION_FIRST_SAMPLES = 16


class SDFModel(Model):
    has_density = True
    has_sdf = True
    has_point_colors = True

    def __init__(self, cfg: SDFConfig, scene: SceneInfo):
        super().__init__()
        self.cfg = cfg = fit_schedules(cfg, SCHEDULE_FRACTIONS)
        self._planned = cfg  # as fitted to the planned run (`replan` starts from it)
        self.scene = scene
        self.register_buffer("aabb", scene.aabb.clone().float())
        self.register_buffer("background", scene.background.clone().float())
        self.register_buffer("centre", self.aabb.mean(0))
        extent = self.aabb[1] - self.aabb[0]
        self.half_size = float(extent.max()) / 2  # R: world per box unit
        # Every ray must enter the box outside the initial surface: a sphere poking out of a flat
        # box's short side makes the box's face itself the first surface each ray meets, and the
        # colours are painted there (a box-shaped level set that never leaves it).
        radius = cfg.init_radius * float(extent.min()) / 2 / self.half_size
        self.field = SDFField(
            cfg.n_levels,
            cfg.n_features,
            cfg.log2_table_size,
            cfg.n_min,
            cfg.n_max,
            cfg.width,
            cfg.n_hidden,
            cfg.geo_features,
            radius,
        )
        self.color_mlp = mlp(
            cfg.geo_features + 3 + num_sh_bases(cfg.sh_degree), cfg.color_width, cfg.color_hidden, 3
        )
        self.log_beta = nn.Parameter(torch.tensor(math.log(cfg.beta_init)))
        self.occupancy = OccupancyGrid(cfg.occupancy_res)
        seeds = points_in_box(scene)
        if seeds is not None:
            self.occupancy.seed(self.to_unit(seeds.to(self.aabb)), 2)
        self.environment = (
            EnvironmentMap() if learns_background(cfg.background, scene.unbounded) else None
        )
        check_random_background(cfg.random_background)
        self.random_background = cfg.random_background
        if cfg.outer_volume not in ("on", "off"):
            raise ValueError(f"outer_volume must be on or off, got {cfg.outer_volume!r}")
        self.outer = None
        if cfg.outer_volume == "on":  # it carries its own environment map
            self.outer, self.environment = (
                OuterVolume(self.aabb, scene.near, scene.far, n_max=cfg.outer_n_max),
                None,
            )
        if cfg.mask_weight < 0:
            raise ValueError(f"mask_weight must be >= 0, got {cfg.mask_weight}")
        self.box_scene = replace(scene, unbounded=False)  # the field ends at the box
        diag = (self.aabb[1] - self.aabb[0]).norm().item()
        self.step_size = diag / cfg.march_steps
        self.beta_min = cfg.beta_min_steps * self.step_size / self.half_size
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.n_rays = cfg.rays_per_batch
        self._samples = 0  # the last step's samples (the next batch's size follows them)

    # ---- the field in the scene's units ------------------------------------------------------
    def to_field(self, points: Tensor) -> Tensor:
        """Scene points (N, 3) -> the field's [-1, 1]^3 (the box's longest side, isotropic)."""
        return (points - self.centre) / self.half_size

    def to_unit(self, points: Tensor) -> Tensor:
        """Scene points (N, 3) -> the occupancy grid's unit cube (the scene box)."""
        return scene_to_unit_cube(points, self.aabb, False)

    def beta(self) -> Tensor:
        return self.log_beta.exp().clamp_min(self.beta_min)

    def sdf(self, points: Tensor) -> Tensor:
        """Signed distance (N,) in scene units at scene points (N, 3), negative inside."""
        return self.field.sdf(self.to_field(points)) * self.half_size

    def density(self, points: Tensor) -> Tensor:
        """VolSDF density (N,) per scene unit at scene points (N, 3)."""
        return volsdf_density(self.field.sdf(self.to_field(points)), self.beta()) / self.half_size

    def _density_unit(self, u: Tensor) -> Tensor:
        """Density per scene unit at points (M, 3) of the occupancy grid's unit cube."""
        return self.density(self.aabb[0] + u * (self.aabb[1] - self.aabb[0]))

    def sdf_gradient(self, points: Tensor) -> Tensor:
        """grad f (N, 3) at scene points (N, 3): the outward normal (unit where eikonal)."""
        return sdf_and_gradient(self.field, self.to_field(points), create_graph=False)[1]

    def point_colors(self, points: Tensor) -> Tensor:
        """rgb (N, 3) at surface points seen head-on (view direction -normal): vertex colours."""
        x = self.to_field(points)
        _, grad, feature = sdf_and_gradient(self.field, x, create_graph=False)
        view = -torch.nn.functional.normalize(grad, dim=-1)
        return self._radiance(feature, grad, sh_basis(self.cfg.sh_degree, view))

    def _radiance(self, feature: Tensor, grad: Tensor, dir_enc: Tensor) -> Tensor:
        return torch.sigmoid(self.color_mlp(torch.cat([feature, grad, dir_enc], -1)))

    # ---- marching ----------------------------------------------------------------------------
    def _march_fn(self, origins: Tensor, directions: Tensor, jitter: bool) -> MarchFn:
        """The rays' march through the occupied cells of the box (`recon.volrend.occupancy`)."""
        t_min, t_max = ray_bounds(self.box_scene, origins, directions, self.aabb)
        u = uniform((origins.shape[0],), t_min, self.generator) if jitter else None

        @torch.no_grad()
        def march(ids: Tensor, k: int):
            o, d = origins[ids], directions[ids]
            ri, t0, t1 = self.occupancy.march(
                o,
                d,
                t_min[ids],
                t_max[ids],
                self.aabb,
                False,
                self.step_size,
                0.0,
                None if u is None else u[ids],
                k,  # march_terminated caps it at max_samples_per_ray
            )
            return ri, t0, t1, o[ri] + (0.5 * (t0 + t1))[:, None] * d[ri]

        return march

    def _kept_samples(self, origins: Tensor, directions: Tensor, jitter: bool):
        """Packed samples early termination keeps: (ray_indices, t_starts, t_ends, points)."""
        ri, t0, t1, x, _ = march_terminated(
            self._march_fn(origins, directions, jitter),
            self.density,
            origins.shape[0],
            self.cfg.eps_transmittance,
            TERMINATION_FIRST_SAMPLES,
            self.cfg.max_samples_per_ray,
            origins.device,
        )
        return ri, t0, t1, x

    def background_colour(self, directions: Tensor) -> Tensor:
        return self.background if self.environment is None else self.environment(directions)

    def _render_rays(
        self, origins: Tensor, directions: Tensor, training: bool, background: Tensor | None = None
    ):
        """-> (VolumeRender, grad f (N, 3) at the rendered samples); composited on `background`
        (3,) or (R, 3), by default the model's (`background_colour`)."""
        ri, t0, t1, x = self._kept_samples(origins, directions, jitter=training)
        sdf, grad, feature = sdf_and_gradient(self.field, self.to_field(x), create_graph=training)
        sigma = volsdf_density(sdf, self.beta()) / self.half_size
        dir_enc = sh_basis(self.cfg.sh_degree, directions)[ri]
        rgb = self._radiance(feature, grad, dir_enc)
        bg = background
        if bg is None:
            bg = self._behind_box(origins, directions, training)
        return volume_render(sigma, rgb, t0, t1, ri, origins.shape[0], bg), grad

    def _behind_box(self, origins: Tensor, directions: Tensor, training: bool) -> Tensor:
        """What each ray (R,) sees behind the box: the outer volume's colour (R, 3) when it is
        on, else `background_colour`."""
        if self.outer is None:
            return self.background_colour(directions)
        t_min, t_max = ray_bounds(self.box_scene, origins, directions, self.aabb)
        t_start = self.outer.start(origins, directions, t_max, t_max > t_min)
        return self.outer(origins, directions, t_start, training, self.generator)

    @property
    def learns_background(self) -> bool:
        return self.environment is not None or self.outer is not None

    def _surface_points_loss(self, data: TrainData) -> Tensor:
        """mean |f| (in box half-sizes) over points_per_step of the data's surface points: the
        zero level set is pulled through what multi-view stereo found (0 without them)."""
        points = data.surface_points
        if points is None or len(points) == 0 or self.cfg.points_weight <= 0:
            return self.log_beta.new_zeros(())
        g = self.generator
        pick = torch.randint(
            0, len(points), (self.cfg.points_per_step,), generator=g, device=g.device
        )
        return self.field.sdf(self.to_field(points[pick.to(points.device)])).abs().mean()

    # ---- Model interface ---------------------------------------------------------------------
    def replan(self, schedule_steps: int, step: int) -> int:
        cfg = refit_schedules(self._planned, self.cfg, REPLAN_FRACTIONS, schedule_steps, step)
        if cfg == self.cfg:
            return 0
        self.cfg = cfg
        return cfg.schedule_steps

    def step_pixels(self, data: TrainData) -> int:
        c = self.cfg
        return batch_pixels(
            c.samples_per_batch, SDFConfig.samples_per_batch, RAYS_PER_STEP, self.n_rays
        )

    def optimizers(self) -> dict[str, OptimizerSpec]:
        cfg = self.cfg
        schedule = lambda step: exp_decay_lr(step, cfg.lr, cfg.lr_final, cfg.lr_decay_steps)
        nets = [*self.field.parameters(), *self.color_mlp.parameters()]
        for extra in (self.environment, self.outer):
            if extra is not None:
                nets += list(extra.parameters())
        grid = self.field.grid.table
        groups = [
            ParamGroup("grid", [grid], schedule),
            ParamGroup("mlp", [p for p in nets if p is not grid], schedule),
            ParamGroup("beta", [self.log_beta], cfg.lr_beta),
        ]
        return {"main": OptimizerSpec(groups, betas=(0.9, 0.99), eps=1e-15)}

    def before_step(self, data: TrainData, step: int) -> None:
        cfg = self.cfg
        if step % cfg.occupancy_every == 0:
            self.occupancy.update(
                self._density_unit,
                self.step_size,
                step < cfg.occupancy_warmup,
                cfg.occupancy_decay,
                cfg.occupancy_threshold,
                generator=self.generator,
            )
        self.field.active_levels = active_levels(
            step, cfg.levels_start, cfg.n_levels, cfg.levels_steps
        )

    def training_loss(
        self, data: TrainData, step: int, background: TrainingBackground
    ) -> tuple[Tensor, dict]:
        cfg = self.cfg
        n_rays = self.n_rays
        batch = sample_rays(data, n_rays, self.generator)
        target, colours = background.targets(batch, self.generator)
        out, grad = self._render_rays(batch["origins"], batch["directions"], True, colours)
        mse = torch.mean((out.rgb - target) ** 2)
        mask = out.acc.new_zeros(())
        if cfg.mask_weight > 0 and data.alpha is not None:
            mask = mask_loss(out.acc, batch["alpha"])
        g = self.generator
        box = torch.rand(cfg.eikonal_points, 3, generator=g, device=g.device) * 2 - 1
        _, box_grad, _ = sdf_and_gradient(self.field, box.to(self.aabb), create_graph=True)
        eikonal = eikonal_loss(torch.cat([grad, box_grad]))
        on_points = self._surface_points_loss(data)
        loss = mse + cfg.eikonal_weight * eikonal + cfg.mask_weight * mask
        loss = loss + cfg.points_weight * on_points
        n_samples = self._samples = grad.shape[0]
        return loss, {  # tensors where a float would sync: the loop reads them when it logs
            "loss": loss.detach(),
            "psnr": training_psnr(mse),
            "eikonal": eikonal.detach(),
            "surface_points": on_points.detach(),
            "beta": self.beta().detach().double() * self.half_size,
            "samples_per_ray": n_samples / n_rays,
            "rays": n_rays,
            "occupied": self.occupancy.occupancy_fraction(),
        }

    def after_step(self, data, step, optimizers, stats) -> None:
        samples_per_batch, n_rays = self.cfg.samples_per_batch, self.n_rays
        if samples_per_batch > 0:  # keep the rendered samples per step, not the rays, fixed
            wanted = samples_per_batch * n_rays / max(self._samples, 1)
            self.n_rays = int(min(max(wanted, n_rays / 2, 64), 2 * n_rays, 1 << 16))

    @torch.no_grad()
    def render(self, camera: Cameras) -> dict[str, Tensor]:
        def rays_fn(o: Tensor, d: Tensor):  # the normals' gradient is taken inside, with grad on
            out, _ = self._render_rays(o, d, training=False)
            return out.rgb, out.depth, out.acc

        return render_image(rays_fn, camera.to(self.aabb.device), self.cfg.chunk)

    def training_state(self) -> dict:
        return {
            "generator": self.generator.get_state(),
            "n_rays": self.n_rays,
            "schedules": schedule_state(self.cfg, SCHEDULE_FRACTIONS),
        }

    def load_training_state(self, state: dict) -> None:
        self.generator.set_state(state["generator"])
        self.n_rays = int(state["n_rays"])
        if "schedules" in state:  # as re-planned (`replan`) by the step it was saved at
            self.cfg = replace(self.cfg, **state["schedules"])

    def stats(self) -> dict[str, float]:
        return {
            "parameters": float(sum(p.numel() for p in self.parameters())),
            "occupied_fraction": float(self.occupancy.occupancy_fraction()),
            "beta": self.beta().item() * self.half_size,
        }


def active_levels(step: int, start: int, n_levels: int, steps: int) -> int:
    """Hash levels in use at `step`: `start`, rising linearly to all `n_levels` at `steps`
    (Neuralangelo's coarse-to-fine, Li et al. 2023, Sec. 3.2, on a CPU run's schedule).
    Example: start 8 of 16 over 2,000 steps: 8 at step 0, 12 at 1,000, 16 from 2,000 on."""
    if start >= n_levels or step >= steps:
        return n_levels
    return start + (n_levels - start) * step // steps


def build(config: SDFConfig, scene: SceneInfo) -> SDFModel:
    return SDFModel(config, scene)


# Rays per second on a 2-thread CPU, measured: lego-200, 10 min, 2 threads, 256 marching steps
# (1,761 steps, 5.65 M rays in 541 s of steps): 10.5 k rays/s, so a 600 s budget is about 1.5
# passes over its 4 M training pixels at full size. With the fused encoding + Jacobian pass the
# same protocol trains 19-21 k rays/s (2,044 / 2,170 steps, 10.6 / 11.9 M rays in 561 / 564 s;
# the shell thins as training goes on, so a later step holds more rays). The policy keeps the
# older, lower rate: a finer level for real captures is a change to measure on them first.
# The throughput probe's first steps on lego-200 and fox alike, 2 threads: 132 ms.
RAYS_PER_STEP = 1024  # a step of the default sample target (`step_pixels`)
RESOLUTION = ResolutionPolicy(
    pixels_per_s=10e3,
    pixels_per_step=RAYS_PER_STEP,
    min_epochs=1.0,
    max_side=800,
    probe_pixels_per_s=7.8e3,
)
SPEC = register(
    MethodSpec(
        name="sdf",
        plans_schedules=True,
        config_cls=SDFConfig,
        build=build,
        presets=PRESETS,
        resolution=RESOLUTION,
        uses_surface_points=True,
    )
)
