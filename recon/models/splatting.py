"""`--method 3dgs`: the Gaussian-splatting Model (Kerbl et al. 2023, "3D Gaussian Splatting for
Real-Time Radiance Field Rendering"), registered at import. Its flat config and presets are in
`splatting_config`, the pure rules it applies to them (rates, extent, "auto") in
`splatting_rules`.

A training step renders one full training view (shuffled epoch order), takes
loss = (1 - lambda) L1 + lambda (1 - SSIM), runs fused Adam with the reference's per-attribute
learning rates (means scaled by the scene extent, decayed exponentially), and lets
`densify.post_step` clone, split, prune and reset.

With `pose_refine` the step also learns a correction of the training view's pose
(`recon.cameras.pose_refine`) with its own Adam (`pose_lr`). Against a scene still being fitted,
an exact camera's photometric optimum is a quarter of a pixel to a pixel away, so exact cameras
refined from the start wander and the scene follows them, and holding only the cameras whose
correction stayed small still costs (bench/results/3dgs_pose_refine.md). So cameras start on
probation (`PoseCorrection.observe` / `release`): for pose_probation_passes passes their images are formed
at the given poses while each camera's pose gradient there is summed; then only the cameras
whose mean gradient is more than pose_release_ratio times the median camera's are refined, and
the others keep their given poses. A released camera gets one Adam step per visit (lr_pose,
decayed only in the second half of lr_decay_steps: it needs tens of visits to come back). On
sample_data (35 views at 100 px, 800 steps) a camera off by 1 deg and 2 % of the scene is the only
one released after 4 passes and comes back 6.7x / 15.6x with the exact cameras untouched;
lego-200's exact cameras stay below 3.6x, so none moves. It stays off by
default: fox's sfm poses are already good to ~0.1 deg and refinement did not help there.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
from torch import Tensor, nn
from torch.profiler import record_function

from recon import devices
from recon.cameras import Cameras
from recon.cameras.pose_refine import PoseCorrection, correct_cameras
from recon.gaussians import densify, gsplat_glue
from recon.gaussians.coarse_to_fine import c2f_factor
from recon.gaussians.contribution import contributions, least_contributing
from recon.gaussians.footprint import with_training_footprint
from recon.gaussians.init import (
    gaussians_from_points,
    gaussians_from_splat_ply,
    initial_gaussians,
    sample_in_hull,
    sample_in_shell,
    uses_random_init,
)
from recon.gaussians.mip_filter import sampling_intervals, smoothed
from recon.gaussians.optim import keep_rows
from recon.gaussians.render import (
    ProjectedSplats,
    composite_rgb,
    composite_rgbd,
    mean_compensation,
    project_splats,
)
from recon.metrics.image import training_psnr
from recon.models.appearance import AppearanceCorrection
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
from recon.models.schedules import (
    fit_schedules,
    refit_schedules,
    schedule_state,
)
from recon.models.splatting_config import (
    EXTENT_RULES,
    PRESETS,
    GaussiansConfig,
    schedule_fractions,
)
from recon.models.splatting_rules import (
    SCENE_RATES,
    anneal_factor,
    densify_strategy,
    means_lr,
    photometric_loss,
    pose_lr,
    pose_probation_end,
    prune_fraction,
    scene_extent,
    scene_lrs,
    uses_antialiasing,
    uses_appearance,
    view_for_step,
)
from recon.volrend import surface_depth


class GaussianModel(Model):
    """G Gaussians as an `nn.ParameterDict` of (G, ...) tensors: means, quats (w, x, y, z),
    log_scales, opacity_logits, sh_dc (G, 1, 3), sh_rest (G, (degree+1)^2 - 1, 3)."""

    exports_splats = True
    aliases_when_minified = True

    def __init__(self, config: GaussiansConfig, scene: SceneInfo):
        super().__init__()
        self._fractions = schedule_fractions(config)
        self.config = config = fit_schedules(config, self._fractions)
        self._planned = config  # as fitted to the planned run (`replan` starts from it)
        self.strategy = densify_strategy(config, bool(scene.unbounded))
        self.antialiased = uses_antialiasing(config, bool(scene.unbounded))
        self.register_buffer("background", scene.background.float().clone())
        self.register_buffer("scene_extent", torch.zeros(()))  # set at the first step
        self._extent = 0.0  # its value on the host, from `before_step` on
        self.register_buffer("active_sh_degree", torch.zeros((), dtype=torch.long))
        # (G,) each Gaussian's finest training sampling interval (filter_3d > 0; `_update_filter`)
        self.register_buffer("filter_intervals", torch.zeros(0))
        self._aabb = scene.aabb.float().clone()
        self._unbounded = bool(scene.unbounded)
        if config.extent not in EXTENT_RULES:
            raise ValueError(
                f"extent must be one of {', '.join(EXTENT_RULES)}, got {config.extent!r}"
            )
        self._points = scene.points  # for the scene extent at the first step (`scene_extent`)
        self._min_sh_degree = 0  # a PLY start keeps the SH degrees it already has
        if config.init_ply:
            if scene.scene_from_world is None:
                raise ValueError("init_ply needs the scene's scene_from_world similarity")
            start, self._min_sh_degree = gaussians_from_splat_ply(
                config.init_ply, scene.scene_from_world, config.sh_degree
            )
            self._random_init = False
            self.active_sh_degree.fill_(self._min_sh_degree)
        else:
            start = initial_gaussians(config, scene)
            self._random_init = uses_random_init(config, scene)
        self.params = nn.ParameterDict({k: nn.Parameter(v) for k, v in start.items()})
        if config.pose_refine and not (
            config.lr_pose > 0
            and config.lr_pose_final > 0
            and config.pose_refine_start >= 0
            and config.pose_release_ratio >= 0
        ):
            raise ValueError(
                "pose_refine needs lr_pose > 0, lr_pose_final > 0, pose_refine_start >= 0 "
                "and pose_release_ratio >= 0"
            )
        self.anneal = anneal_factor(config, bool(scene.unbounded))
        if not (0.0 <= config.prune_contribution < 1.0 or config.prune_contribution == -1.0):
            raise ValueError(
                f"prune_contribution must be in [0, 1) or -1 (auto), got {config.prune_contribution}"
            )
        self.prune_fraction = prune_fraction(config, scene)
        # (C, 6) twists of the training cameras, sized at the first step (`_train_camera`)
        self.pose_correction = PoseCorrection(0) if config.pose_refine else None
        # (C, 3, 4) colour corrections of the training images, sized at the first step too
        self.appearance = (
            AppearanceCorrection(0, config.lr_appearance)
            if uses_appearance(config, scene)
            else None
        )
        self._reset_training_state()

    def _reset_training_state(self) -> None:
        """The densification accumulators, for the Gaussians as they stand (the trainer gives
        replaced parameters a fresh optimizer)."""
        self.densify_state = densify.init_state(self.num_gaussians, self.params["means"].device)

    def optimizers(self) -> dict[str, OptimizerSpec]:
        """Adam per attribute with the reference's rates (eps 1e-15, fused: one pass over memory
        per tensor, ~4x faster than the per-op loop on a 2-core CPU at 50k Gaussians): the
        means' decaying with the scene extent (`means_lr`), the others annealed on unbounded
        captures (`scene_lrs`); the pose corrections' and colour corrections' Adams beside."""
        c, anneal = self.config, self.anneal
        base = {"means": c.lr_means, **{g: getattr(c, f) for g, f in SCENE_RATES.items()}}

        def rate(name: str):
            if name == "means":
                return lambda step: means_lr(c, step, self._extent)
            if anneal != 1.0:
                return lambda step: scene_lrs(c, step, anneal)[name]
            return base[name]

        groups = [ParamGroup(name, [p], rate(name)) for name, p in self.params.items()]
        specs = {"main": OptimizerSpec(groups, eps=1e-15, fused=True)}
        if self.pose_correction is not None:
            twists = [self.pose_correction.twists]
            pose = ParamGroup("pose", twists, lambda step: pose_lr(c, step))
            specs["pose"] = OptimizerSpec([pose], eps=1e-15)
        if self.appearance is not None:
            deltas = ParamGroup("appearance", [self.appearance.deltas], self.appearance.lr)
            specs["appearance"] = OptimizerSpec([deltas], eps=1e-15)
        return specs

    @property
    def bakes_view_terms(self) -> bool:
        """Antialiased: `splats(cameras)` bakes the compensation's mean into the opacities."""
        return self.antialiased

    @property
    def num_gaussians(self) -> int:
        return self.params["means"].shape[0]

    def gaussians(self) -> dict[str, Tensor]:
        """The attribute tensors `render.project_splats` takes: the parameters, with filter_3d
        their scales and opacities after the 3D smoothing filter (`mip_filter.smoothed`)."""
        g = dict(self.params.items())
        if self.config.filter_3d > 0 and len(self.filter_intervals) == self.num_gaussians:
            g["log_scales"], g["opacity_logits"] = smoothed(
                g["log_scales"], g["opacity_logits"], self.filter_intervals, self.config.filter_3d
            )
        return g

    @torch.no_grad()
    def _update_filter(self, data: TrainData, step: int | None = None) -> None:
        """filter_3d: the sampling intervals of the Gaussians in the training cameras (as the
        model sees them: `train_cameras`) when Gaussians were added or removed, and after every
        densify_interval-th `step` (as Mip-Splatting recomputes its filter every 100 steps)."""
        if self.config.filter_3d <= 0:
            return
        stale = len(self.filter_intervals) != self.num_gaussians
        due = step is not None and (step + 1) % max(self.config.densify_interval, 1) == 0
        if stale or due:
            means = self.params["means"].detach()
            cameras = self.train_cameras(data.cameras).to(means.device)
            self.filter_intervals = sampling_intervals(means, cameras, near=self.config.near_plane)

    @torch.no_grad()
    def splats(self, cameras: Cameras | None = None) -> dict:
        """The Gaussians as rendered (filter_3d baked in), as numpy arrays. An antialiased
        model given its training `cameras` has the compensation baked into its opacities:
        sigmoid(logit) times its mean over the views (`render.mean_compensation`), so that a
        viewer that does not compensate shows it as training did, on average."""
        g = {k: v.detach() for k, v in self.gaussians().items()}
        if self.bakes_view_terms and cameras is not None:
            comp = mean_compensation(g, self.train_cameras(cameras), self.config.near_plane)
            opacity = torch.sigmoid(g["opacity_logits"].double().cpu()) * comp
            logits = torch.log(opacity) - torch.log1p(-opacity)
            g["opacity_logits"] = logits.to(g["opacity_logits"])
        p = {k: v.cpu().numpy() for k, v in g.items()}
        return {
            "means": p["means"],
            "quats": p["quats"],
            "log_scales": p["log_scales"],
            "opacity_logits": p["opacity_logits"].reshape(-1),
            "sh": np.concatenate([p["sh_dc"], p["sh_rest"]], axis=1),
        }

    def before_step(self, data: TrainData, step: int) -> None:
        self._extent = self._prepare_step(data, step)

    def training_loss(
        self, data: TrainData, step: int, background: TrainingBackground
    ) -> tuple[Tensor, dict]:
        """One view, full resolution. The `3dgs.*` profiler labels split the step's time (see
        pipelines/bench_gaussians.py)."""
        c = self.config
        view = view_for_step(step, len(data), c.seed)
        short_side = min(data.images.shape[1:3])
        level = data.downsampled(c2f_factor(step, c.c2f_factor, c.c2f_interval, short_side))
        self._update_filter(data)  # first step, or resumed
        with record_function("3dgs.project"):
            height, width = level.images.shape[1:3]  # not read from the camera: a GPU sync
            splats = project_splats(
                self.gaussians(),
                self._train_camera(level, view, step),
                self._sh_degree(step),
                c.near_plane,
                self.antialiased,
                (width, height),
            )
        splats.means2d.retain_grad()
        abs_grad = torch.zeros_like(splats.means2d) if self.strategy.uses_abs_grad else None
        with record_function("3dgs.rasterize"):
            rgb, _ = composite_rgb(splats, background.colour, abs_grad)
        rgb = self._corrected(rgb, view, data.cameras)
        target = level.images[view]
        with record_function("3dgs.loss"):
            loss = photometric_loss(rgb, target, c.ssim_weight)
            if (regularizer := self.strategy.regularizer(self.params)) is not None:
                loss = loss + regularizer
        with torch.no_grad():
            mse = torch.mean((rgb.clamp(0, 1) - target) ** 2)
        self._last = (splats, abs_grad, view)  # for `after_step`'s densification
        return loss, {  # 0-d tensors where a float would sync: the loop reads them when it logs
            "loss": loss.detach(),
            "psnr": training_psnr(mse),
        }

    def optimizers_due(self, step: int) -> set[str]:
        """The Gaussians' and the colour corrections' every step; the pose corrections' from
        pose_refine_start, after their probation (`pose_probation_end`)."""
        due = {"main", "appearance"}
        if self.pose_correction is not None and step >= pose_probation_end(
            self.config, len(self.pose_correction.twists)
        ):
            due.add("pose")
        return due

    def after_step(self, data, step, optimizers, stats) -> None:
        splats, abs_grad, view = self._last
        self._last = None
        with record_function("3dgs.optimizer"):
            self._pose_step(step, view)
        with record_function("3dgs.densify"):
            self._densify(optimizers["main"], splats, abs_grad, step, self._extent)
            self._update_filter(data, step)
            # only where densification ran (not in a run too short to densify)
            ending = step + 1 == self.strategy.stop > self.strategy.start
            if ending and self.prune_fraction > 0:
                self._prune_by_contribution(optimizers["main"], data)
                self._update_filter(data)
        stats["num_gaussians"] = float(self.num_gaussians)

    def averaging(self, step: int) -> float:
        """average_window of the planned run (schedule_steps, else default_steps), from the step
        on which densification stopped changing the count (`Strategy.stop`)."""
        c = self.config
        if c.average_window <= 0 or step < self.strategy.stop:
            return 0
        return max(1.0, c.average_window * (c.schedule_steps or c.default_steps))

    def replan(self, schedule_steps: int, step: int) -> int:
        config = refit_schedules(self._planned, self.config, self._fractions, schedule_steps, step)
        if config == self.config:
            return 0
        self.config = config
        self.strategy = densify_strategy(config, self._unbounded)
        return config.schedule_steps

    def _train_camera(self, data: TrainData, view: int, step: int) -> Cameras:
        """Training view `view`'s camera; with pose_refine, corrected by its learnt twist (and
        differentiable in it) from pose_refine_start on."""
        if self.pose_correction is None:
            return data.cameras[view]
        count = len(self.pose_correction.twists)
        if count == 0:  # first step: a zero twist per camera, pivots at the scene box's centre
            self.pose_correction.reset(data.cameras, self._aabb.mean(0))
        elif count != len(data):
            raise ValueError(
                f"the model holds pose corrections of {count} training cameras "
                f"but is trained on {len(data)}"
            )
        elif self.pose_correction.gauge is None:  # loaded from a checkpoint
            self.pose_correction.set_gauge(data.cameras)
        if step < self.config.pose_refine_start or bool(self.pose_correction.frozen[view]):
            return data.cameras[view]
        return self.pose_correction(data.cameras, [view])

    def _corrected(self, rgb: Tensor, view: int, cameras: Cameras) -> Tensor:
        """The render of training view `view` (of the training `cameras`) after its learnt colour
        correction (appearance on); `render` corrects other views by their neighbours'."""
        if self.appearance is None:
            return rgb
        if len(self.appearance.deltas) == 0:  # first step: an identity per training image
            self.appearance.reset(cameras)
        elif len(self.appearance.deltas) != len(cameras):
            raise ValueError(
                f"the model holds colour corrections of {len(self.appearance.deltas)} "
                f"training images but is trained on {len(cameras)}"
            )
        return self.appearance(rgb, view)

    def _pose_step(self, step: int, view: int) -> None:
        """On probation (`pose_probation_end`): sum the view's pose gradient (the trainer moves
        nothing) and at its last step `release` the outlier cameras; after it, once the
        trainer's Adam step moved the free cameras' twists, hold the others and the gauge."""
        if self.pose_correction is None or step < self.config.pose_refine_start:
            return
        end = pose_probation_end(self.config, len(self.pose_correction.twists))
        if step < end:
            self.pose_correction.observe(view)
            if step + 1 == end:
                self.pose_correction.release(self.config.pose_release_ratio)
            return
        self.pose_correction.hold_frozen()
        self.pose_correction.remove_gauge()

    def train_cameras(self, cameras: Cameras, positions: list[int] | None = None) -> Cameras:
        """The training cameras at `positions` of the training split (default: all, in
        order) as the model learnt them: corrected by those cameras' pose twists if
        pose_refine, else unchanged. Other cameras take no correction."""
        if self.pose_correction is None or len(self.pose_correction.twists) == 0:
            return cameras
        positions = list(range(len(cameras))) if positions is None else positions
        if len(positions) != len(cameras):
            raise ValueError(f"{len(cameras)} cameras but {len(positions)} positions")
        twists = self.pose_correction.twists
        picked = torch.as_tensor(positions, dtype=torch.long, device=twists.device)
        with torch.no_grad():
            return correct_cameras(
                cameras.to(twists.device), twists[picked], self.pose_correction.pivots[picked]
            )

    def _prepare_step(self, data: TrainData, step: int) -> float:
        """Scene extent (`scene_extent`, once; the means' learning rate scales with it) and SH
        degree for `step`."""
        c = self.config
        if step == 0 and self._random_init and c.init_from_images:
            self._init_from_images(data)
        # the float32 buffer's value, read from the device once (and again after a load), so a
        # resumed run sees the same extent
        if devices.host_value(self, "extent", self.scene_extent, float) == 0.0:
            self.scene_extent.fill_(scene_extent(data.cameras, self._points, c.extent))
        extent = devices.host_value(self, "extent", self.scene_extent, float)
        device = self.params["means"].device
        if self.densify_state["grad2d"].device != device:  # the model was moved after init
            self.densify_state = {k: v.to(device) for k, v in self.densify_state.items()}
        self.active_sh_degree.fill_(self._sh_degree(step))
        return extent

    def _sh_degree(self, step: int) -> int:
        """The SH degree trained at `step`: one more every sh_degree_interval steps."""
        c = self.config
        scheduled = min(c.sh_degree, step // max(c.sh_degree_interval, 1))
        return max(scheduled, self._min_sh_degree)

    @torch.no_grad()
    def _init_from_images(self, data: TrainData) -> None:
        """Replace the random Gaussians by ones sampled in the training images' visual hull and
        coloured by them (`init.sample_in_hull`): far fewer wasted splats when the capture is
        composited on a plain background, image colours otherwise. Unbounded captures put
        `init_far_fraction` of them in a shell beyond the cameras (`init.sample_in_shell`):
        the background, which the scene box leaves out, starts with Gaussians too."""
        c = self.config
        n_far = int(c.init_points * c.init_far_fraction) if self._unbounded else 0
        points, colors = sample_in_hull(
            self._aabb, c.init_points - n_far, data.images, data.cameras, self.background, c.seed
        )
        if n_far:
            far, far_colors = sample_in_shell(
                self._aabb.mean(0),
                data.cameras.centers,
                c.init_far_factor,
                n_far,
                data.images,
                data.cameras,
                c.seed + 1,
            )
            points, colors = torch.cat([points, far]), torch.cat([colors, far_colors])
        if len(points) < 4:  # nothing but background: keep the random start
            return
        device = self.params["means"].device
        fresh = gaussians_from_points(points, colors, c.sh_degree, c.init_opacity)
        for name, value in fresh.items():
            self.params[name] = nn.Parameter(value.to(device))
        self._reset_training_state()

    @torch.no_grad()
    def _prune_by_contribution(self, optimizer: torch.optim.Adam, data: TrainData) -> None:
        """Drop the `prune_fraction` of Gaussians with the least blending weight summed over the
        training views (as the model sees them: pose corrections applied)."""
        scores = contributions(
            self.gaussians(),
            self.train_cameras(data.cameras),
            int(self.active_sh_degree),
            self.config.near_plane,
            self.antialiased,
        )
        drop = least_contributing(scores, self.prune_fraction)
        keep_rows(self.params, optimizer, ~drop.to(self.params["means"].device))
        self.densify_state = densify.init_state(self.num_gaussians, self.params["means"].device)

    def _densify(
        self,
        optimizer: torch.optim.Adam,
        splats: ProjectedSplats,
        abs_grad: Tensor | None,
        step: int,
        extent: float,
    ) -> None:
        gen = torch.Generator(device=self.params["means"].device)
        gen.manual_seed(self.config.seed + 7919 * step)
        lr = means_lr(self.config, step, extent)
        self.densify_state = self.strategy.post_backward(
            self.params, optimizer, self.densify_state, splats, abs_grad, step, extent, lr, gen
        )

    @torch.no_grad()
    def render(self, camera: Cameras) -> dict[str, Tensor]:
        """rgb (H, W, 3), depth (H, W) = expected z / acc where acc > 0 (else 0), acc (H, W).
        The camera is used as given: no pose correction (see `train_cameras`). With appearance,
        rgb takes the colour correction of the nearest training photos (`models.appearance`)."""
        degree = int(self.active_sh_degree)
        c = self.config
        device = self.params["means"].device
        splats = project_splats(
            self.gaussians(), camera.to(device), degree, c.near_plane, self.antialiased
        )
        if c.footprint_filter and len(self.filter_intervals) == self.num_gaussians:
            focal = float(camera.K[0, 0, 0])
            splats = with_training_footprint(splats, self.filter_intervals, focal, self.antialiased)
        out = composite_rgbd(splats, self.background)
        acc = out["acc"]
        depth = surface_depth(out["depth"], acc)
        rgb = out["rgb"]
        if self.appearance is not None and len(self.appearance.deltas):
            rgb = self.appearance.for_camera(rgb, camera)  # nearest training photos' exposure
        return {"rgb": rgb, "depth": depth, "acc": acc}

    def splat_rendering(self) -> dict:
        footprint = (
            self.config.footprint_filter and len(self.filter_intervals) == self.num_gaussians
        )
        return {
            "sh_degree": int(self.active_sh_degree),
            "antialiased": bool(self.antialiased),
            "background": [float(x) for x in self.background.cpu()],
            "near": float(self.config.near_plane),
            "intervals": self.filter_intervals.cpu().numpy() if footprint else None,
        }

    @torch.no_grad()
    def finish(self, data: TrainData) -> dict[str, float]:
        """With footprint_filter: each Gaussian's finest sampling interval over the training
        views, for `render` (`footprint.with_training_footprint`; filter_3d keeps its own up to
        date while it trains). The training views render as before."""
        stale = len(self.filter_intervals) != self.num_gaussians
        if self.config.footprint_filter and (self.config.filter_3d <= 0 or stale):
            means = self.params["means"].detach()
            cameras = self.train_cameras(data.cameras).to(means.device)
            self.filter_intervals = sampling_intervals(means, cameras, near=self.config.near_plane)
        return {}

    def training_state(self) -> dict:
        return {
            "densify": {k: v.clone() for k, v in self.densify_state.items()},
            "schedules": schedule_state(self.config, self._fractions),
        }

    def load_training_state(self, state: dict) -> None:
        self.densify_state = {
            k: v.to(self.params["means"].device) for k, v in state["densify"].items()
        }
        if "schedules" in state:  # as re-planned (`replan`) by the step it was saved at
            self.config = replace(self.config, **state["schedules"])
            self.strategy = densify_strategy(self.config, self._unbounded)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Resize the Gaussian tensors to the saved count first (densification changes it), then
        load; the accumulators restart for the new tensors (and the trainer's optimizers:
        `Trainer.load_state_dict` restores both)."""
        for name, p in self.params.items():
            saved = state_dict.get(f"params.{name}")
            if saved is not None and saved.shape != p.shape:
                self.params[name] = nn.Parameter(p.new_empty(saved.shape))
        saved = state_dict.get("filter_intervals")
        if saved is not None:
            self.filter_intervals = saved.new_empty(saved.shape)
        else:  # saved before the filter existed: recomputed at the next training step
            state_dict = {**state_dict, "filter_intervals": self.filter_intervals.new_zeros(0)}
        saved = state_dict.get("pose_correction.twists")
        if self.pose_correction is not None and saved is not None:  # sized at the first step
            self.pose_correction.resize(len(saved))
            older = {  # saved before cameras could be held, or before the probation
                "pose_correction.frozen": torch.zeros(len(saved), dtype=torch.bool),
                "pose_correction.grad_sums": torch.zeros(len(saved), 6, dtype=torch.float64),
                "pose_correction.visits": torch.zeros(len(saved), dtype=torch.int64),
            }
            state_dict = {**older, **state_dict}
        saved = state_dict.get("appearance.deltas")
        if self.appearance is not None and saved is not None:
            self.appearance.resize(len(saved))
        result = super().load_state_dict(state_dict, strict=strict, assign=assign)
        self._reset_training_state()
        return result

    def stats(self) -> dict[str, float]:
        """Size, and with pose_refine how far the poses moved (`PoseCorrection.stats`)."""
        pose = self.pose_correction.stats() if self.pose_correction is not None else {}
        colour = (
            self.appearance.spread()
            if self.appearance is not None and len(self.appearance.deltas)
            else {}
        )
        return {
            "parameters": float(sum(p.numel() for p in self.params.values())),
            "gaussians": float(self.num_gaussians),
            **pose,
            **colour,
        }


def build(config: GaussiansConfig, scene: SceneInfo) -> GaussianModel:
    return GaussianModel(config, scene)


# The working resolution: one whole image a step at ~450k px/s (the quiet fox-real benchmark
# measured 530k px/s at 215 x 382, 500k at 179 x 319 and 300k at 107 x 191; 350k, measured on
# a loaded machine, chose one level too coarse at 2 and 10 minutes). The step plan: a step's
# wall time is affine in its pixels, 50 ms + 1 us a pixel (a least-squares fit to the four
# fox-real runs, 76-278 ms a step from 25k to 228k pixels, within 8 %), where the one rate
# had planned 2,099 steps for a 10-minute run that made 3,642, and 2,758 for 30 minutes that
# made 6,479: the densification stopped and the lr decayed long before the end. The throughput
# probe's first steps, same machine: 8.2 ms + 1 / 1.9M s a pixel, fitted to both benchmark
# scenes (fox's 13.6k sfm Gaussians of the earlier sfm settings 6-14 % faster than that, today's
# 7.9k about the same; lego-200's 4k random ones 9 % slower), so either sits well inside the
# prior's tolerance.
RESOLUTION = ResolutionPolicy(
    pixels_per_s=450e3,
    pixels_per_step=0.0,
    min_epochs=30.0,
    # a step fits one view; past ~100 views (lego's, more than fox's 58) 30 passes over every
    # one would put a many-photo capture at a far coarser level for the same number of steps
    # (spiral-300, 262 views, 10 min: 1/7) where the reference trains 30,000 steps whatever
    # the number of views
    epoch_views=100,
    # detailed photos (each pyramid level holds detail the next lacks): 50 views, about
    # fox's 58, so that a many-photo capture trains at the level an ordinary one would; on
    # spiral-300 (262 views of 800 x 600, 29 dB detail) 30 minutes at full size scored 0.95 dB
    # over the 1/2 of 100 views at the photos' size, where on fox (42 dB: smooth phone
    # photos) 1/2 instead of 1/3 gained nothing (bench/results/2026-11-29-spiral-30min-level.md)
    detail_views=50,
    max_side=1600,
    step_overhead_s=0.05,
    step_pixels_per_s=1.0e6,
    probe_overhead_s=0.0082,
    probe_pixels_per_s=1.9e6,
    # the probe starts from at most fox's ~8k sfm points: spiral-300's 31.9k (300 photos)
    # made its probe steps 2.4x fox's, read as a machine 0.35x as fast, where its full-size run
    # stepped faster than the plan at the reference's speed (0.46 s against 0.53)
    probe_points=8000,
)
SPEC = register(
    MethodSpec(
        name="3dgs",
        plans_schedules=True,
        config_cls=GaussiansConfig,
        build=build,
        presets=PRESETS,
        resolution=RESOLUTION,
        starts_from_splats=True,
        cuda_missing=gsplat_glue.cuda_missing,
    )
)
