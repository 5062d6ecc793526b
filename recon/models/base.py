"""The contract between the `train` / `render` / `mesh` stages and a scene representation.

The stages never see a representation's internals: they hand it `TrainData` and cameras and
get images back. Each method module (`nerf`, `ngp`, `plenoxel`, `gaussians`) registers a
`(Config, Model)` pair with `register`.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from recon.cameras import Cameras
from recon.cameras.rays import rays_from_pixels
from recon.devices import generator_on


@dataclass
class SceneInfo:
    """What every representation may know about the normalized scene.

    aabb: (2, 3) box [min, max] that holds the scene in the normalized frame (usually [-1, 1]^3).
    unbounded: the capture is a real, unbounded scene: use a contraction outside the box.
    background: (3,) colour composited behind the scene (training images were composited on it).
    near, far: ray bounds in normalized units.
    points, point_colors: optional (P, 3) SfM points (normalized frame) and colours in [0, 1].
    scene_from_world: the normalization, for inputs given in world units (a splat PLY to start from).
    """

    aabb: Tensor
    unbounded: bool
    background: Tensor
    near: float
    far: float
    points: Tensor | None = None
    point_colors: Tensor | None = None
    scene_from_world: object | None = (
        None  # cameras.similarity.Similarity, x_scene = s R x_world + t
    )


@dataclass
class TrainData:
    """Training images and their cameras, on the training device.

    images: (C, H, W, 3) float32 in [0, 1], already composited on `SceneInfo.background`.
    cameras: C pinhole cameras of size (W, H).
    alpha: (C, H, W) float32 coverage where the photos had an alpha channel, else None (a
    model may then composite them on other backgrounds: `recomposite`).
    surface_points: (N, 3) points on the scene's surfaces found by multi-view stereo (`recon
    mvs`), in the scene frame, or None; a model may pin its surface to them.
    """

    images: Tensor
    cameras: Cameras
    alpha: Tensor | None = None
    surface_points: Tensor | None = None
    _levels: dict = field(default_factory=dict, repr=False)

    def __len__(self) -> int:
        return self.images.shape[0]

    def downsampled(self, factor: int) -> TrainData:
        """The same views area-downsampled by the integer `factor` (W // f x H // f pixels, the
        intrinsics scaled exactly: `Cameras.resized`), computed once: the targets of
        coarse-to-fine training."""
        if factor == 1:
            return self
        if factor not in self._levels:
            import numpy as np

            from recon.io.images import resize_area

            _, H, W, _ = self.images.shape
            w, h = max(1, W // factor), max(1, H // factor)
            small = np.stack([resize_area(im, w, h) for im in self.images.cpu().numpy()])
            alpha = None
            if self.alpha is not None:
                alpha = np.stack([resize_area(a, w, h) for a in self.alpha.cpu().numpy()])
                alpha = torch.from_numpy(alpha).to(self.images.device)
            self._levels[factor] = TrainData(
                torch.from_numpy(small).to(self.images.device),
                self.cameras.resized(w, h),
                alpha,
                self.surface_points,
            )
        return self._levels[factor]

    @property
    def num_pixels(self) -> int:
        return self.images.shape[0] * self.images.shape[1] * self.images.shape[2]

    def rays_at(self, index: Tensor) -> dict[str, Tensor]:
        """The rays of training pixels given by flat indices (N,) into (C, H, W), computed on
        demand (a stored table of every pixel would hold ~36 bytes a pixel: 144 MB for 100
        views at 200 x 200): origins (N, 3), directions (N, 3) unit, z_per_t (N,), rgb (N, 3),
        camera (N,) int64, and alpha (N,) where the data has it. Example: with C = 2 views of
        2 x 3 pixels, index 7 is camera 1, row 0, column 1, through the pixel centre (1.5, 0.5)."""
        H, W = self.images.shape[1:3]
        index = index.to(self.images.device)
        camera, pixel = index // (H * W), index % (H * W)
        uv = torch.stack([pixel % W, pixel // W], dim=-1).float() + 0.5
        o, d, z = rays_from_pixels(
            uv, self.cameras.K[camera].float(), self.cameras.world_from_cam[camera].float()
        )
        rays = {
            "origins": o,
            "directions": d,
            "z_per_t": z,
            "rgb": self.images.reshape(-1, 3)[index],
            "camera": camera,
        }
        if self.alpha is not None:
            rays["alpha"] = self.alpha.reshape(-1)[index]
        return rays

    def rays(self) -> dict[str, Tensor]:
        """Every training pixel's ray (`rays_at` of all of them), in (C, H, W) order."""
        return self.rays_at(torch.arange(self.num_pixels, device=self.images.device))


def recomposite(rgb: Tensor, alpha: Tensor, old: Tensor, new: Tensor) -> Tensor:
    """Pixels composited on `old` moved onto `new`: a c + (1 - a) old -> a c + (1 - a) new, i.e.
    rgb + (1 - a) (new - old), exact without dividing by a. rgb (N, 3), alpha (N,), old (3,),
    new (3,) or (N, 3). Example: rgb 0.6 = 0.5 * 0.2 + 0.5 * 1 on white, onto black -> 0.1."""
    return rgb + (1.0 - alpha)[:, None] * (new - old)


@dataclass(frozen=True)
class TrainingBackground:
    """What a training step's rays composite on, chosen for the run by the trainer
    (`recon.train.trainer.training_background`): the scene's `colour` (3,), which the photos
    were composited on, or with `random` one random colour a ray (Instant-NGP's training of
    synthetic scenes, Mueller et al. 2022), each target moved onto its ray's colour
    (`recomposite`: the photos' alpha is needed)."""

    colour: Tensor
    random: bool = False

    def targets(
        self, batch: dict[str, Tensor], generator: torch.Generator
    ) -> tuple[Tensor, Tensor | None]:
        """A ray batch's targets (N, 3) and the colours (N, 3) its rays composite on (None: the
        model's own, `colour`): with `random` each ray draws its colour from `generator` and
        its target (`TrainData.rays_at`, with "alpha") moves onto it."""
        target = batch["rgb"]
        if not self.random:
            return target, None
        g = generator
        new = torch.rand(target.shape[0], 3, generator=g, device=g.device).to(target)
        return recomposite(target, batch["alpha"], self.colour.to(target), new), new


@dataclass
class ParamGroup:
    """Parameters one optimizer updates at one learning rate: `lr` a number, or a schedule
    (step -> learning rate) the trainer evaluates before every update."""

    name: str
    params: list[Tensor]
    lr: float | Callable[[int], float]
    weight_decay: float = 0.0


@dataclass
class OptimizerSpec:
    """An optimizer over `groups`: Adam (Kingma & Ba 2015; `betas`, `eps`, `fused`: torch's
    single-kernel update) or, with kind "sgd", plain gradient descent."""

    groups: list[ParamGroup]
    betas: tuple[float, float] = (0.9, 0.999)
    eps: float = 1e-8
    fused: bool | None = None
    kind: str = "adam"


class Model(nn.Module):
    """A trainable scene. Subclasses implement the methods below.

    Training is split as nerfstudio splits it (Model / Trainer): the trainer
    (`recon.train.trainer`) owns the optimizers, applies the learning-rate schedules, steps,
    and saves and restores the optimizer state; a model supplies its parameter groups with
    their schedules (`optimizers`), its loss (`training_loss`) and the callbacks around the
    update (`before_step`, `after_backward`, `after_step`: batching, occupancy grids,
    densification and pruning). `training_loss` returns the loss and scalars for the log (at
    least "loss"): Python numbers where the host already knows them (a tensor's shape), else
    detached 0-d tensors on the model's device, which the loop reads (one host sync) only on
    the steps it logs. A step on a GPU makes no host round trip of its own
    (`tests/models/test_device_clean.py`).
    `render` returns, for ONE camera, "rgb" (H, W, 3), "depth" (H, W) as z-depth along the
    optical axis in normalized units, and "acc" (H, W) accumulated opacity.

    What a model can do beyond that it declares in the capability flags below; stages ask them
    (a mesh from the density field, a splat export) instead of testing a method's name.
    """

    has_density: bool = False  # `density(points)` is defined: marching cubes on the field
    has_sdf: bool = False  # `sdf(points)` is defined: the surface is its zero level set
    has_point_colors: bool = False  # `point_colors(points)` is defined: coloured mesh vertices
    has_radiance: bool = False  # `radiance(points, directions)` is defined: a bake to voxels
    exports_splats: bool = False  # `splats()` returns its Gaussians (the splat PLY export)
    # `splats(cameras)` folds a view-dependent render-time term into its values, averaged over
    # the cameras (3dgs's antialiasing compensation): the export passes the training views
    bakes_view_terms: bool = False
    # Its renders at a coarser level than it trained at are not faithful: 3DGS dilates every
    # projected Gaussian by 0.3 px, which thickens and brightens the splats that minification
    # makes sub-pixel (the "dilation" artefact of zooming out, Yu et al. 2024, Mip-Splatting).
    # Coarse views are rendered at the training level and area-downsampled instead, as the
    # photos of that level were made.
    aliases_when_minified: bool = False
    background: Tensor  # (3,) buffer: the scene's colour, composited behind everything it renders
    # Its config's random_background ("auto" | "on" | "off"; "off" where a method has no such
    # option): whether the trainer composites training rays on random colours
    # (`TrainingBackground`); `learns_background`: an environment map is its background.
    random_background: str = "off"
    learns_background: bool = False

    def plan_note(self, data: TrainData) -> str | None:
        """What the model chose from the training data before its first step, and why (one
        line the train stage logs), or None."""
        return None

    def step_pixels(self, data: TrainData) -> int:
        """The training pixels (rays) the next step fits: one whole image by default;
        a model that samples ray batches, its batch (the throughput probe counts them,
        `recon.train.throughput`)."""
        return data.images.shape[1] * data.images.shape[2]

    def optimizers(self) -> dict[str, OptimizerSpec]:
        """Its optimizers by name ("main", and any others, e.g. pose corrections), as they stand:
        the trainer builds a fresh one whenever a spec's parameters are not the tensors it
        updates (a model that replaces its parameters gets fresh moments; one that resizes
        them in place keeps its optimizer's state in step itself, in `after_step`)."""
        raise NotImplementedError

    def before_step(self, data: TrainData, step: int) -> None:
        """Called before the loss of 0-based `step` (occupancy updates, schedules of its own)."""

    def training_loss(
        self, data: TrainData, step: int, background: TrainingBackground
    ) -> tuple[Tensor, dict]:
        """The loss of `step` (a batch or a view of `data`, its rays composited on
        `background`, the trainer's) and the scalars to log."""
        raise NotImplementedError

    def after_backward(self, data: TrainData, step: int, stats: dict) -> None:
        """Called after the backward pass, before the optimizers step (gradients of its own)."""

    def optimizers_due(self, step: int) -> set[str] | None:
        """The optimizers that update at `step` (None: all of them)."""
        return None

    def after_step(
        self, data: TrainData, step: int, optimizers: dict[str, torch.optim.Optimizer], stats: dict
    ) -> None:
        """Called after the update (densification and pruning edit `optimizers`' state)."""

    def averaging(self, step: int) -> float:
        """The window (steps) of the moving average of its parameters that the trainer keeps
        from the end of 0-based `step` on and the run ends as (`recon.train.averaging`), or 0:
        none at `step` (it asks for none, or its parameters may still change shape)."""
        return 0

    @torch.no_grad()
    def render(self, camera: Cameras) -> dict[str, Tensor]:
        raise NotImplementedError

    def train_cameras(self, cameras: Cameras, positions: list[int] | None = None) -> Cameras:
        """The training cameras as the model learnt them: `cameras` are those at `positions`
        in the training split (default: all of it, in order). Models that refine poses return
        them corrected; the others as given."""
        return cameras

    def density(self, points: Tensor) -> Tensor:
        """Volume density sigma (N,) at normalized points (N, 3); models with `has_density`."""
        raise NotImplementedError

    def sdf(self, points: Tensor) -> Tensor:
        """Signed distance (N,) at normalized points (N, 3), negative inside; models with
        `has_sdf`."""
        raise NotImplementedError

    def point_colors(self, points: Tensor) -> Tensor:
        """A view-independent colour (N, 3) in [0, 1] at normalized points (N, 3), for mesh
        vertices; models with `has_point_colors`."""
        raise NotImplementedError

    def radiance(self, points: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        """The field at normalized points (N, 3) seen along each of D unit directions (D, 3):
        sigma (N,) and colour (N, D, 3) in [0, 1]; models with `has_radiance`."""
        raise NotImplementedError

    def splats(self, cameras: Cameras | None = None) -> dict:
        """The Gaussians (as a viewer without the model's own render-time terms should draw
        them over the training `cameras`, when given) as numpy arrays in the scene frame (means (G, 3), quats wxyz (G, 4),
        log_scales (G, 3), opacity_logits (G,), sh (G, K, 3)); models with `exports_splats`."""
        raise NotImplementedError

    def splat_rendering(self) -> dict:
        """How its own `render` draws `splats()` (models with `exports_splats`), for a viewer
        that projects them itself: "sh_degree", "antialiased" (the per-view opacity
        compensation), "background" (3,) floats, "near", and "intervals" (G,) numpy, each
        Gaussian's finest training sampling interval whose footprint finer views keep (or
        None)."""
        raise NotImplementedError

    def finish(self, data: TrainData) -> dict[str, float]:
        """Called once when training stops, before the model is saved: a last clean-up that
        does not change the renders (e.g. dropping what no training ray sees). Returns stats."""
        return {}

    def file_state(self) -> dict:
        """The state `save_model` writes to model.pt: `state_dict()`, or a smaller form of it
        that `load_state_dict` reads back (checkpoints keep the exact `state_dict()`)."""
        return self.state_dict()

    def training_state(self) -> dict:
        """Everything beyond `state_dict()` and the optimizers (the trainer saves those) needed
        to resume exactly: random generators, schedules, accumulators."""
        return {}

    def load_training_state(self, state: dict) -> None:
        pass

    def replan(self, schedule_steps: int, step: int) -> int:
        """Lay the step schedules fitted to the run's planned length (lr decay, densification)
        out anew, before 0-based `step`, for a run now expected to end after `schedule_steps`
        steps (never longer than planned, `recon.models.schedules.refit_schedules`). Returns
        the run length the schedules now follow if they changed, else 0 (also: no such
        schedules)."""
        return 0

    def _apply(self, fn, recurse: bool = True):
        """`nn.Module.to` / `.cuda()` / `.cpu()`: the torch.Generators the model owns follow its
        tensors to their device (`recon.devices.generator_on`), so random numbers are drawn
        where they are used. A model is moved before it trains (its generators still at their
        seeds); a moved generator restarts from its seed."""
        module = super()._apply(fn, recurse)
        tensor = next(itertools.chain(self.parameters(), self.buffers()), None)
        if tensor is not None:
            for name, value in list(vars(self).items()):
                if isinstance(value, torch.Generator):
                    setattr(self, name, generator_on(value, tensor.device))
        return module

    def reseed(self, seed: int) -> None:
        """Reseed every torch.Generator the model owns (after a rollback, retried steps must
        not replay the batches that produced a non-finite loss)."""
        for value in vars(self).values():
            if isinstance(value, torch.Generator):
                value.manual_seed(seed)

    def stats(self) -> dict[str, float]:
        """Size of the model as it stands (parameters, primitives, occupied voxels...)."""
        return {"parameters": sum(p.numel() for p in self.parameters())}


@dataclass(frozen=True)
class ResolutionPolicy:
    """What a method needs from its training images, to choose its working resolution
    (`recon.train.resolution`): how many training pixels it gets through per second, how many
    passes over every pixel it needs to fit a resolution, and the longest side it trains on
    when no time budget bounds the run. The rates are whole runs' averages on the reference
    machine (2 threads of the benchmark VM's CPU); a run elsewhere scales them by the speed
    its throughput probe measures against the probe's time there (`recon.train.throughput`)."""

    pixels_per_s: float = 350e3  # training pixels (rays) per second on the reference machine
    pixels_per_step: float = 0.0  # pixels per step for a --steps run (0: one whole image per step)
    min_epochs: float = 30.0  # passes over every training pixel the method needs at one size
    # passes are counted over at most this many views (0: all of them): beyond them a capture's
    # views overlap, and more of them add viewpoints of the same surfaces, not more to fit
    epoch_views: int = 0
    # ... or over at most this many (0: epoch_views) at a level whose photos hold detail the
    # next coarser level lacks (`train.resolution.DETAIL_DB`): a finer level there is worth
    # fewer passes, since what it adds is what a render at the photos' size shows
    detail_views: int = 0
    max_side: int = 1600  # longest image side trained on without a time budget
    # The step plan (`planned_steps`, which lays out the step schedules) may take a step's time
    # as affine in its pixels instead: step_overhead_s + pixels / step_pixels_per_s
    step_overhead_s: float = 0.0  # seconds a step costs whatever its size, on the reference
    step_pixels_per_s: float = 0.0  # pixels a second beyond that overhead (0: pixels_per_s)
    # The throughput probe's steps on the reference machine (its first steps, not a run's
    # average): probe_overhead_s + P / probe_pixels_per_s for P pixels a step (the method's
    # pixels_per_step, or the probe image's); 0: never measured, the run takes the prior speed
    probe_overhead_s: float = 0.0
    probe_pixels_per_s: float = 0.0
    # ... with its model built from at most this many sfm points (0: all of them). The probe
    # measures the device, not the scene: a step's cost grows with the model a method starts
    # from its points (3dgs: one Gaussian a point), so a capture of many photos, with several
    # times the points, would read as a slower machine, though its run's model grows to what
    # densification makes of it, about the same from any start
    probe_points: int = 0


@dataclass(frozen=True)
class MethodSpec:
    name: str
    config_cls: type
    build: Callable  # (config, scene: SceneInfo) -> Model
    presets: dict  # preset name -> {field: value} overrides of the config defaults
    resolution: ResolutionPolicy = ResolutionPolicy()  # how the working resolution is chosen
    starts_from_splats: bool = False  # its config takes `init_ply`: a splat PLY to start from
    starts_from_fields: bool = False  # its config takes `bake_from`: a model with `radiance`
    uses_surface_points: bool = False  # its training uses `TrainData.surface_points`
    # its config's `schedule_steps`, left at 0, is the run's planned step count to lay its step
    # schedules out over (filled in by `train.resolution.plan_schedules`; 3dgs, sdf)
    plans_schedules: bool = False
    # what it lacks to run on a CUDA device (a package to install), or None: () -> str | None
    cuda_missing: Callable | None = None


METHODS: dict[str, MethodSpec] = {}


def register(spec: MethodSpec) -> MethodSpec:
    METHODS[spec.name] = spec
    return spec
