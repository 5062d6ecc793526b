"""`--method 3dgs`: the Gaussian-splatting Model (Kerbl et al. 2023, "3D
Gaussian Splatting for Real-Time Radiance Field Rendering"), its flat config and presets, registered at import.

A training step renders one full training view (shuffled epoch order), takes
loss = (1 - lambda) L1 + lambda (1 - SSIM), runs fused Adam with the reference's per-attribute
learning rates (means scaled by the scene extent, decayed exponentially), and lets
`densify.post_step` clone, split, prune and reset.

With `pose_refine` the step also learns a correction of the training view's pose
(`recon.cameras.pose_refine`) with its own Adam (`pose_lr`). Against a scene still being fitted,
an exact camera's photometric optimum is a quarter of a pixel to a pixel away, so exact cameras
refined from the start wander and the scene follows them (lego-200, exact poses: 5,400 steps
ended at 31.5 dB against 32.8 without; holding the cameras whose correction stayed below 1.5 px
after 10 passes still cost 0.31 dB at 10 minutes). So cameras start on probation
(`PoseCorrection.observe` / `release`): for pose_probation_passes passes their images are formed
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

from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor, nn
from torch.profiler import record_function

from recon import devices
from recon.cameras import Cameras
from recon.cameras.pose_refine import PoseCorrection, correct_cameras
from recon.gaussians import densify, gsplat_glue, mcmc
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
from recon.gaussians.optim import keep_rows, make_adam
from recon.gaussians.render import (
    ProjectedSplats,
    composite_rgb,
    composite_rgbd,
    mean_compensation,
    project_splats,
)
from recon.gaussians.ssim import ssim
from recon.gaussians.strategy import Strategy
from recon.metrics.image import training_psnr
from recon.models.appearance import AppearanceCorrection
from recon.models.base import MethodSpec, Model, ResolutionPolicy, SceneInfo, TrainData, register
from recon.models.schedules import (
    exp_decay_lr,
    fit_schedules,
    refit_schedules,
    schedule_state,
    set_lr,
)
from recon.options import on_off_auto, opt
from recon.volrend import surface_depth

# A capture whose camera extent is below this fraction of the median depth of its SfM points
# is seen from a small baseline (all cameras looking one way: a forward-facing capture)
FORWARD_FACING_RATIO = 0.5
EXTENT_RULES = ("auto", "cameras", "depth")


# How late in a run of `schedule_steps` steps each step schedule may end (`fit_schedules`,
# schedule_fit "tuned": the fast preset's; "reference" scales the config's own schedules,
# `schedule_fractions`): with the fast preset and a 1,600-step plan: lr_decay_steps 1,600, densify_stop 1,120,
# opacity_reset_interval 560, sh_degree_interval 320.
# measured on fox at 1,600 steps, 269 x 478 (bench/results/3dgs_real_capture.md): densifying
# until 0.7 of the run with the means lr decayed over the whole run beats the lego-tuned steps
# (30.66 against 29.38 dB) and shrinking everything by the same factor (30.51 dB, far fewer
# Gaussians, LPIPS 0.160 against 0.140).
SCHEDULE_FRACTIONS = {
    "lr_decay_steps": 1.0,
    "densify_stop": 0.7,
    "opacity_reset_interval": 0.35,
    "sh_degree_interval": 0.2,
    "relocate_stop": 0.85,
}


SCHEDULE_FITS = ("reference", "tuned")

_DENSIFY = densify.DensifyStrategy  # the densification defaults have one source: the strategy


@dataclass(frozen=True)
class GaussiansConfig:
    """3D Gaussian splatting. Defaults are the reference's (the "paper" preset); "fast" rescales
    the schedules to a CPU run of a few thousand steps, doubles the rates of the means,
    scales and colours and, on real captures, anneals all but the means' over the run's
    second half."""

    init: str = opt("sfm", "sfm (SceneInfo.points; random if there are none) | random")
    init_points: int = opt(100_000, "random initial Gaussians in the scene box")
    init_from_images: bool = opt(False, "random init: sample the visual hull, colours from images")
    init_far_fraction: float = opt(
        0.5, "unbounded scenes: share of image init points in a far shell"
    )
    init_far_factor: float = opt(
        3.0, "the far shell's outer / inner radius (inner: beyond the cameras)"
    )
    init_ply: str = opt(
        "", "start from this INRIA splat PLY (world units, as `recon export` writes)"
    )
    init_opacity: float = opt(0.1, "initial opacity of every Gaussian")
    sh_degree: int = opt(3, "largest SH degree of the colours")
    sh_degree_interval: int = opt(1000, "raise the active SH degree by one every this many steps")
    near_plane: float = opt(0.01, "Gaussians with camera z <= this are culled")
    ssim_weight: float = opt(0.2, "lambda in (1 - lambda) L1 + lambda (1 - SSIM)")
    lr_means: float = opt(0.00016, "means lr at step 0, times the scene extent (`extent`)")
    lr_means_final: float = opt(0.0000016, "means lr after lr_decay_steps, times the scene extent")
    lr_decay_steps: int = opt(30_000, "steps of the exponential decay of the means lr")
    lr_sh_dc: float = opt(0.0025, "lr of the degree-0 SH coefficients")
    lr_sh_rest: float = opt(0.000125, "lr of the degree 1-3 SH coefficients (dc / 20)")
    lr_opacity: float = opt(0.05, "lr of the opacity logits")
    lr_scales: float = opt(0.005, "lr of the log-scales")
    lr_quats: float = opt(0.001, "lr of the quaternions")
    lr_anneal: float = opt(
        1.0,
        "the rates of the scales, rotations, opacities and colours at lr_decay_steps, as a fraction of their own (log-linear decay over its second half; 1 = constant, as the reference; -1 = auto: 0.1 on unbounded captures, 1 on bounded scenes)",
    )
    densify_grad_threshold: float = opt(
        _DENSIFY.grad_threshold, "mean NDC 2D-mean gradient that triggers densify"
    )
    densify_dense_fraction: float = opt(
        _DENSIFY.dense_fraction, "clone below this x extent (max scale), split above"
    )
    densify_start: int = opt(_DENSIFY.start, "first densification step")
    densify_stop: int = opt(_DENSIFY.stop, "no densification or opacity reset from this step")
    densify_interval: int = opt(_DENSIFY.interval, "steps between densifications")
    opacity_reset_interval: int = opt(_DENSIFY.reset_interval, "steps between opacity resets")
    prune_opacity: float = opt(_DENSIFY.prune_opacity, "prune Gaussians less opaque than this")
    prune_screen_fraction: float = opt(
        _DENSIFY.prune_screen_fraction, "prune if screen radius > this x image size (after a reset)"
    )
    prune_world_fraction: float = opt(
        _DENSIFY.prune_world_fraction, "prune if max scale > this x extent (after a reset)"
    )
    max_gaussians: int = opt(_DENSIFY.max_gaussians, "densification stops growing the count here")
    clone_opacity_correction: bool = opt(
        _DENSIFY.clone_opacity_correction,
        "a clone and its original share the opacity (1 - sqrt(1 - o))",
    )
    densify_abs_grad: str = opt(
        "off",
        "densify by the absolute per-pixel 2D-mean gradients (AbsGS): on | off | auto (on for unbounded captures)",
    )
    densify_abs_grad_threshold: float = opt(
        0.0006, "the densify threshold when densifying by absolute gradients"
    )
    densify_pixel_weights: bool = opt(
        _DENSIFY.pixel_weights,
        "average the densify gradient over views weighted by each view's screen area (Pixel-GS)",
    )
    densify_mode: str = opt(
        "adc",
        "how the Gaussian count is controlled: adc (clone, split, prune; Kerbl et al.) | mcmc (relocation of dead Gaussians, growth to max_gaussians, position noise; Kheradmand et al.) | auto (mcmc for unbounded captures)",
    )
    mcmc_growth: float = opt(0.05, "mcmc: each refinement adds this fraction of the count")
    mcmc_noise_lr: float = opt(5e5, "mcmc: the position noise's scale, times the means lr")
    mcmc_opacity_reg: float = opt(
        mcmc.McmcStrategy.opacity_reg, "mcmc: weight of the L1 penalty on the opacities"
    )
    mcmc_scale_reg: float = opt(
        mcmc.McmcStrategy.scale_reg, "mcmc: weight of the L1 penalty on the scales"
    )
    relocate_stop: int = opt(25_000, "mcmc: no relocation or growth from this step on")
    schedule_steps: int = opt(
        0,
        "the run's planned length (recon train sets it from the budget): longer step schedules are fitted into it (0 = as configured)",
    )
    schedule_fit: str = opt(
        "reference",
        "how step schedules longer than schedule_steps are fitted into it: reference (each scaled by schedule_steps / default_steps: the reference's proportions, densifying until half the run) | tuned (each ended at its share of the run in SCHEDULE_FRACTIONS, measured on CPU runs of a few thousand steps)",
        choices=SCHEDULE_FITS,
    )
    c2f_factor: int = opt(
        1, "coarse-to-fine: the first steps fit targets downscaled by this (1 = off)"
    )
    c2f_interval: int = opt(
        250, "coarse-to-fine: steps at each coarse level (the factor halves after each)"
    )
    appearance: str = opt(
        "off",
        "per-image affine colour correction of the training photos: on | off | auto (on for unbounded captures)",
    )
    lr_appearance: float = opt(0.001, "lr of the appearance corrections")
    prune_contribution: float = opt(
        -1.0,
        "when densification ends, drop this fraction of the Gaussians, those with the least blending weight over the training views (-1 = auto: 0.5 for bounded scenes, 0 for unbounded captures)",
    )
    pose_refine: bool = opt(False, "learn an SE(3) correction of each training camera's pose")
    lr_pose: float = opt(
        0.003, "lr of the pose corrections (radians and scene units), a step per visit of a camera"
    )
    lr_pose_final: float = opt(
        0.00003, "pose lr at lr_decay_steps (log-linear decay over its second half)"
    )
    pose_refine_start: int = opt(0, "first step of the pose probation")
    pose_probation: int = opt(
        -1,
        "steps during which the poses stay as given while their gradients are summed (-1 = pose_probation_passes passes over the training views; 0 = none: every camera is refined)",
    )
    # pose_probation_passes: passes over the training views of the pose probation (each
    # camera's gradient summed over as many visits). Measured
    # (bench/results/3dgs_pose_refine.md), the largest outlier ratio of an exact camera and of one off by 1 deg and 2 % of the scene: sample_data after 4 passes 2.1x /
    # 5.9x, after 5.7 passes 2.4x / 9.7x, after 10 passes 2.8x / 16x; lego-200's 100 exact cameras
    # after 4, 5 and 10 passes at most 4.1x, 4.4x and 4.1x. Released after 5 passes the perturbed
    # camera comes back 7.6x / 20x in an 800-step run; after 10 passes the scene has fitted its
    # wrong pose and it comes back only 1.0x / 2.3x (lr 3e-3). The fast preset's doubled scene rates
    # (2026-11-28) fit the wrong pose sooner: released after 5 passes the camera came back only
    # 3.3x / 6.7x, after 4 passes 6.7x / 15.6x (3 passes: 4.5x / 7.2x); lego-200's exact cameras at
    # most 3.56x after 4 passes and 3.75x after 5 with those rates, so none is released. With the
    # reference's rates 4 passes are too few (the camera stays frozen), so the default (the paper
    # preset's) is 5 and the fast preset's 4.
    pose_probation_passes: int = opt(5, "the probation's passes when pose_probation is -1")
    pose_release_ratio: float = opt(
        6.0,
        "after the probation only cameras whose mean pose gradient is more than this many times the median camera's are refined; the others keep their given poses (0 = refine every camera, no probation)",
    )
    antialiased: str = opt(
        "auto",
        "on | off | auto (on for real captures, off for synthetic scenes): scale each splat's opacity by sqrt(det Sigma / det(Sigma + 0.3 I)) so the dilation keeps its integral (gsplat's antialiased mode, Mip-Splatting's 2D filter normalisation); exports bake its mean over the training views into the opacities, as other viewers do not compensate",
    )
    filter_3d: float = opt(
        0.0,
        "Mip-Splatting's 3D smoothing filter: each Gaussian convolved with an isotropic one of this many squared training sampling intervals (0 = off; the paper's 0.2). Exports carry it baked in, so an init_ply from one should train with 0",
    )
    footprint_filter: bool = opt(
        True,
        "renders finer than the training views keep each splat's training footprint: its 0.3 px^2 dilation held in world units (0.3 (f T / z)^2 px^2 where the render samples a Gaussian finer than its finest training view did, T that view's sampling interval); renders at the training size are unchanged",
    )
    extent: str = opt(
        "auto",
        "the scene length the means lr and the densification's size thresholds scale with: cameras (the reference's camera extent) | depth (the SfM points' median depth) | auto (depth for a forward-facing capture, whose camera spread is under half that depth)",
        choices=EXTENT_RULES,
    )
    seed: int = opt(0, "seeds random init, view order and split sampling")
    default_steps: int = opt(30_000, "steps when `recon train` is given no stopping rule")


PRESETS = {
    "paper": {"prune_contribution": 0.0},
    "fast": {
        "init_points": 4000,
        "init_from_images": True,
        "sh_degree_interval": 500,
        "lr_decay_steps": 5000,
        "densify_start": 100,
        "densify_stop": 2000,
        "relocate_stop": 2500,  # mcmc: the paper's 25 k of 30 k steps, at default_steps
        "densify_interval": 100,
        "opacity_reset_interval": 1000,
        "max_gaussians": 200_000,
        "default_steps": 3000,
        "schedule_fit": "tuned",
        "clone_opacity_correction": True,
        # a lower split/clone threshold than the reference's 0.0002: at 0.0002 the count stops
        # growing long before a CPU run ends (fox: 93 k Gaussians at 10 min, 96 k at 30); with
        # 0.00015 (bench/results/3dgs_c2f_ab.md, 10 min each) fox keeps 131 k (LPIPS 0.0996
        # against 0.1053, 32.33 against 32.52 dB; 2 min 27.42 against 27.09 dB) and lego-200
        # 57 k (33.43 against 33.22 dB, LPIPS 0.0108 against 0.0118)
        "densify_grad_threshold": 0.00015,
        # twice the reference's rates for the means, scales and colours (opacity and rotations
        # unchanged): they are tuned for 30 k steps and a CPU run makes 1.5-8 k. Measured in
        # pairs, same seed (bench/results/3dgs_lr_scale.md): fox-real 2 min +0.13 dB, 10 min
        # +0.12 and -0.04 dB, 30 min +0.56 (2.8 k steps) and +0.06 dB (4.8 k steps), LPIPS lower
        # in all five; lego-200 10 min +0.89 dB (34.00, LPIPS 0.0089 against 0.0118); x4 lost
        # 0.22 dB on fox at 10 min
        "lr_means": 0.00032,
        "lr_means_final": 0.0000032,
        "lr_scales": 0.01,
        "lr_sh_dc": 0.005,
        "lr_sh_rest": 0.00025,
        # and on real captures all but the means' (which decay 100x over the run) anneal to a
        # tenth over the run's second half, in place of the reference's constant rates: one
        # image a step at these rates leaves the opacities and scales jittering (fox-real +0.39
        # and +0.47 dB at 10 and 30 min; lego-200 -0.39 dB, so auto; see anneal_factor)
        "lr_anneal": -1.0,
        # at these rates the scene fits a wrong camera pose sooner: a shorter pose probation
        # (bench/results/3dgs_pose_refine.md; see pose_probation_passes above)
        "pose_probation_passes": 4,
        # no coarse-to-fine: at equal wall time on fox it saved 34 s over the first 500 steps
        # and lost them again to larger Gaussians (same steps, 32.48 vs 32.52 dB without;
        # bench/results/3dgs_c2f_ab.md)
        "appearance": "auto",
        # AbsGS densification on real captures only: fox-real 10 min +0.11 dB, LPIPS 0.115
        # against 0.120; lego-200 -0.15 dB (bench/results/3dgs_absgrad.md)
        "densify_abs_grad": "auto",
    },
}
# What `--preset auto` means on a GPU: the reference's settings and schedules (scaled into the
# planned steps), plus what a real capture needs that the reference's synthetic and curated
# scenes did not: per-photo exposure compensation, AbsGS densification and the annealed rates,
# each "auto" (real captures only: a synthetic scene trains as with "paper"). On fox at 3,000
# steps they gave +0.6 dB over "paper" (bench/results/2026-11-28-3dgs-gpu-preset.md).
PRESETS["gpu"] = {
    **PRESETS["paper"],
    "appearance": "auto",
    "densify_abs_grad": "auto",
    "lr_anneal": -1.0,
}


def schedule_fractions(config: GaussiansConfig) -> dict[str, float]:
    """How late in a planned run each step schedule may end (`fit_schedules`): schedule_fit
    "tuned" -> SCHEDULE_FRACTIONS; "reference" -> each schedule's own share of default_steps,
    so a planned run shorter than that keeps the config's proportions (the paper preset, INRIA's
    30,000 steps: the means' lr decayed over the whole run, densification until half of it, an
    opacity reset every tenth, an SH degree more every thirtieth, mcmc relocation until 5/6).
    Example: the paper preset planned at 12,000 steps -> lr_decay_steps 12,000, densify_stop
    6,000, opacity_reset_interval 1,200, sh_degree_interval 400, relocate_stop 10,000."""
    if config.schedule_fit == "tuned":
        return SCHEDULE_FRACTIONS
    if config.schedule_fit != "reference":
        raise ValueError(
            f"schedule_fit must be one of {', '.join(SCHEDULE_FITS)}, got {config.schedule_fit!r}"
        )
    return {name: getattr(config, name) / config.default_steps for name in SCHEDULE_FRACTIONS}


def photometric_loss(rgb: Tensor, target: Tensor, ssim_weight: float) -> Tensor:
    """(1 - lambda) |rgb - target|_1 + lambda (1 - SSIM(rgb, target)), SSIM with the 11x11
    Gaussian window, sigma 1.5, valid windows (`ssim.py`, the twin of pytorch_msssim).
    (H, W, 3) -> ()."""
    l1 = (rgb - target).abs().mean()
    if ssim_weight == 0:
        return l1
    s = ssim(rgb.permute(2, 0, 1), target.permute(2, 0, 1))
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - s)


def camera_extent(cameras: Cameras) -> float:
    """1.1 x the largest distance of a camera centre from their mean (the reference's
    `cameras_extent`); 1 for a single camera."""
    centers = cameras.centers.double()
    radius = (centers - centers.mean(0)).norm(dim=-1).max().item()
    return 1.1 * radius if radius > 1e-9 else 1.0


def median_point_depth(cameras: Cameras, points: Tensor, max_points: int = 20_000) -> float:
    """The median z-depth of `points` (P, 3) over the cameras (C) they are in front of (at most
    `max_points`, evenly strided); 0 when none is in front of any camera."""
    pts = points[:: max(1, len(points) // max_points)].double()
    M = cameras.cam_from_world.double()
    z = (pts @ M[:, :3, :3].transpose(1, 2))[..., 2] + M[:, None, :3, 3][..., 2]  # (C, P)
    z = z[z > 0]
    return float(z.median()) if len(z) else 0.0


def scene_extent(cameras: Cameras, points: Tensor | None, rule: str) -> float:
    """The length the means' lr and the densification's size thresholds are measured in:
    "cameras" -> `camera_extent` (the reference's; for a capture around an object, about the
    object's distance); "depth" -> 1.1 x the median depth of the SfM points; "auto" -> "depth"
    for a forward-facing capture (camera extent < FORWARD_FACING_RATIO x that depth, where the
    cameras' spread says nothing of the scene's size: llff_flower 0.073 against 0.81), else
    "cameras". Without points, "cameras"."""
    if rule not in EXTENT_RULES:
        raise ValueError(f"extent must be one of {', '.join(EXTENT_RULES)}, got {rule!r}")
    cams = camera_extent(cameras)
    if rule == "cameras" or points is None or len(points) == 0:
        return cams
    depth = 1.1 * median_point_depth(cameras, points)
    if depth <= 0:
        return cams
    if rule == "depth" or cams < FORWARD_FACING_RATIO * depth:
        return depth
    return cams


def means_lr(config: GaussiansConfig, step: int, extent: float) -> float:
    """Log-linear decay lr_means -> lr_means_final over lr_decay_steps, times the extent."""
    return extent * exp_decay_lr(
        step, config.lr_means, config.lr_means_final, config.lr_decay_steps
    )


SCENE_RATES = {  # parameter group -> its config rate; the means have their own decay (means_lr)
    "quats": "lr_quats",
    "log_scales": "lr_scales",
    "opacity_logits": "lr_opacity",
    "sh_dc": "lr_sh_dc",
    "sh_rest": "lr_sh_rest",
}


def anneal_factor(config: GaussiansConfig, unbounded: bool) -> float:
    """lr_anneal, or with -1 (auto) 0.1 on unbounded captures and 1 (constant rates) on bounded
    scenes. Measured (bench/results/3dgs_lr_anneal.md), 0.1 against 1: fox-real 10 min 32.70
    against 32.31 dB, 30 min 33.51 against 33.04; lego-200 10 min 33.61 against 34.00."""
    if config.lr_anneal == -1.0:
        return 0.1 if unbounded else 1.0
    if not config.lr_anneal > 0:
        raise ValueError(f"lr_anneal must be > 0 or -1 (auto), got {config.lr_anneal}")
    return config.lr_anneal


def scene_lrs(config: GaussiansConfig, step: int, anneal: float) -> dict[str, float]:
    """The rates of the non-position parameter groups at `step`: their config values until
    lr_decay_steps / 2, then a log-linear decay to `anneal` times those at lr_decay_steps.
    Example: lr_opacity 0.05, anneal 0.1, lr_decay_steps 1,000 -> 0.05 at step 500, 0.0158
    at step 750, 0.005 from step 1,000 on."""
    begin = config.lr_decay_steps // 2
    rates = {}
    for group, field in SCENE_RATES.items():
        lr = getattr(config, field)
        rates[group] = exp_decay_lr(step, lr, lr * anneal, config.lr_decay_steps, begin)
    return rates


def pose_lr(config: GaussiansConfig, step: int) -> float:
    """lr_pose over the first half of [pose_refine_start, lr_decay_steps], then a log-linear
    decay to lr_pose_final at its end: a camera is visited once per pass over the training
    views and needs tens of updates to come back, so the decay waits; then it stops the
    corrections' jitter."""
    begin = (config.pose_refine_start + config.lr_decay_steps) // 2
    return exp_decay_lr(step, config.lr_pose, config.lr_pose_final, config.lr_decay_steps, begin)


def pose_probation_end(config: GaussiansConfig, num_cameras: int) -> int:
    """The first step after the pose probation: pose_refine_start + pose_probation steps
    (-1: pose_probation_passes passes over the num_cameras training views); with
    pose_release_ratio 0 there is none (pose_refine_start). Example: 35 cameras, the
    defaults (5 passes) -> 175."""
    if config.pose_release_ratio <= 0:
        return config.pose_refine_start
    steps = (
        config.pose_probation_passes * num_cameras
        if config.pose_probation < 0
        else config.pose_probation
    )
    return config.pose_refine_start + steps


def prune_fraction(config: GaussiansConfig, scene: SceneInfo) -> float:
    """prune_contribution, or with -1 (auto) 0.5 for bounded scenes and 0 for unbounded ones.
    Measured at 10 min (bench/results/3dgs_prune_contribution.md): lego-200 keeps 28.3 k
    Gaussians instead of 56.7 k at 33.50 against 33.53 dB (LPIPS 0.0104 both), but fox-real
    loses 0.43 dB (31.99 against 32.43): its short runs leave too few steps to refill the
    background. With densify_mode mcmc, auto is 0: max_gaussians is already the budget."""
    if config.prune_contribution != -1.0:
        return config.prune_contribution
    return 0.0 if scene.unbounded or uses_mcmc(config, bool(scene.unbounded)) else 0.5


def uses_antialiasing(config: GaussiansConfig, unbounded: bool) -> bool:
    """on | off, or auto: on for unbounded captures (real photos: at equal steps on fox-real it
    scores higher at the training size and, with the footprint filter, at the photos' size no
    worse than the training-size render upsampled, where the plain model loses 0.7 dB), off for
    bounded synthetic scenes (lego-200: a worse LPIPS). true / false: configs saved when this
    was a boolean."""
    value = {True: "on", False: "off", "true": "on", "false": "off"}.get(
        config.antialiased, config.antialiased
    )
    return on_off_auto(value, "antialiased", unbounded)


def uses_appearance(config: GaussiansConfig, scene: SceneInfo) -> bool:
    """on | off, or auto: on for unbounded captures (real photos, whose exposure and white
    balance vary), off for bounded scenes with alpha (synthetic renders of known exposure)."""
    return on_off_auto(config.appearance, "appearance", bool(scene.unbounded))


def view_for_step(step: int, n_views: int, seed: int) -> int:
    """Shuffled epochs: a fresh permutation of the views every n_views steps, a pure function
    of (step, seed) so resumed runs visit the same views."""
    gen = torch.Generator().manual_seed(seed * 1_000_003 + step // n_views)
    return int(torch.randperm(n_views, generator=gen)[step % n_views])


def uses_abs_grad(config: GaussiansConfig, unbounded: bool) -> bool:
    """on | off, or auto: on for unbounded captures. At 10 min (bench/results/3dgs_absgrad.md)
    fox-real gains 0.11 dB and LPIPS 0.115 against 0.120 (threshold 0.0006; 0.0004 grew 30 %
    more Gaussians, made fewer steps and lost PSNR), while lego-200 loses 0.15 dB."""
    return on_off_auto(config.densify_abs_grad, "densify_abs_grad", unbounded)


def uses_mcmc(config: GaussiansConfig, unbounded: bool) -> bool:
    """densify_mode adc | mcmc, or auto: mcmc for unbounded captures."""
    modes = {"adc": False, "mcmc": True, "auto": unbounded}
    if config.densify_mode not in modes:
        raise ValueError(f"densify_mode must be adc, mcmc or auto, got {config.densify_mode!r}")
    return modes[config.densify_mode]


def densify_strategy(config: GaussiansConfig, unbounded: bool) -> Strategy:
    if uses_mcmc(config, unbounded):
        return mcmc.McmcStrategy(
            cap=config.max_gaussians,
            growth=config.mcmc_growth,
            min_opacity=config.prune_opacity,
            noise_lr=config.mcmc_noise_lr,
            start=config.densify_start,
            stop=config.relocate_stop,
            interval=config.densify_interval,
            opacity_reg=config.mcmc_opacity_reg,
            scale_reg=config.mcmc_scale_reg,
        )
    abs_grad = uses_abs_grad(config, unbounded)
    return densify.DensifyStrategy(
        grad_threshold=(
            config.densify_abs_grad_threshold if abs_grad else config.densify_grad_threshold
        ),
        dense_fraction=config.densify_dense_fraction,
        prune_opacity=config.prune_opacity,
        prune_screen_fraction=config.prune_screen_fraction,
        prune_world_fraction=config.prune_world_fraction,
        start=config.densify_start,
        stop=config.densify_stop,
        interval=config.densify_interval,
        reset_interval=config.opacity_reset_interval,
        max_gaussians=config.max_gaussians,
        clone_opacity_correction=config.clone_opacity_correction,
        abs_grad=abs_grad,
        pixel_weights=config.densify_pixel_weights,
    )


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
        c = self.config
        lrs = {
            "means": c.lr_means,
            "quats": c.lr_quats,
            "log_scales": c.lr_scales,
            "opacity_logits": c.lr_opacity,
            "sh_dc": c.lr_sh_dc,
            "sh_rest": c.lr_sh_rest,
        }
        self.optimizer = make_adam(self.params, lrs)
        self.densify_state = densify.init_state(self.num_gaussians, self.params["means"].device)
        self._reset_pose_optimizer()

    def _reset_pose_optimizer(self) -> None:
        self.pose_optimizer = None
        if self.pose_correction is not None:
            group = {"params": [self.pose_correction.twists], "name": "pose"}
            self.pose_optimizer = torch.optim.Adam([group], lr=self.config.lr_pose, eps=1e-15)

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

    def train_step(self, data: TrainData, step: int) -> dict[str, float]:
        """One view, full resolution. The `3dgs.*` profiler labels split the step's time (see
        pipelines/bench_gaussians.py)."""
        c = self.config
        extent = self._prepare_step(data, step)
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
            rgb, _ = composite_rgb(splats, self.background, abs_grad)
        rgb = self._corrected(rgb, view, data.cameras)
        target = level.images[view]
        with record_function("3dgs.loss"):
            loss = photometric_loss(rgb, target, c.ssim_weight)
            if (regularizer := self.strategy.regularizer(self.params)) is not None:
                loss = loss + regularizer
        self.optimizer.zero_grad(set_to_none=True)
        with record_function("3dgs.backward"):
            loss.backward()
        with record_function("3dgs.optimizer"):
            self.optimizer.step()
            self._pose_step(step, view)
            self._appearance_step()
        with record_function("3dgs.densify"):
            self._densify(splats, abs_grad, step, extent)
            self._update_filter(data, step)
            # only where densification ran (not in a run too short to densify)
            ending = step + 1 == self.strategy.stop > self.strategy.start
            if ending and self.prune_fraction > 0:
                self._prune_by_contribution(data)
                self._update_filter(data)
        with torch.no_grad():
            mse = torch.mean((rgb.clamp(0, 1) - target) ** 2)
        return {  # 0-d tensors where a float would sync: the loop reads them when it logs
            "loss": loss.detach(),
            "psnr": training_psnr(mse),
            "num_gaussians": float(self.num_gaussians),
        }

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
            self._reset_pose_optimizer()
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

    def _appearance_step(self) -> None:
        if self.appearance is not None:
            self.appearance.optimizer.step()
            self.appearance.optimizer.zero_grad(set_to_none=True)

    def _pose_step(self, step: int, view: int) -> None:
        """On probation (`pose_probation_end`): sum the view's pose gradient, move nothing, and
        at its last step `release` the outlier cameras; after it, an Adam step of the free
        cameras' twists."""
        if self.pose_optimizer is None or step < self.config.pose_refine_start:
            return
        end = pose_probation_end(self.config, len(self.pose_correction.twists))
        if step < end:
            self.pose_correction.observe(view)
            self.pose_optimizer.zero_grad(set_to_none=True)
            if step + 1 == end:
                self.pose_correction.release(self.config.pose_release_ratio)
            return
        set_lr(self.pose_optimizer, pose_lr(self.config, step), "pose")
        self.pose_optimizer.step()
        self.pose_optimizer.zero_grad(set_to_none=True)
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
        """Scene extent (`scene_extent`, once), SH degree and means lr for `step`."""
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
        set_lr(self.optimizer, means_lr(c, step, extent), "means")
        if self.anneal != 1.0:
            for group, lr in scene_lrs(c, step, self.anneal).items():
                set_lr(self.optimizer, lr, group)
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
    def _prune_by_contribution(self, data: TrainData) -> None:
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
        keep_rows(self.params, self.optimizer, ~drop.to(self.params["means"].device))
        self.densify_state = densify.init_state(self.num_gaussians, self.params["means"].device)

    def _densify(
        self, splats: ProjectedSplats, abs_grad: Tensor | None, step: int, extent: float
    ) -> None:
        gen = torch.Generator(device=self.params["means"].device)
        gen.manual_seed(self.config.seed + 7919 * step)
        lr = means_lr(self.config, step, extent)
        self.densify_state = self.strategy.post_backward(
            self.params, self.optimizer, self.densify_state, splats, abs_grad, step, extent, lr, gen
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
        state = {
            "optimizer": self.optimizer.state_dict(),
            "densify": {k: v.clone() for k, v in self.densify_state.items()},
            "schedules": schedule_state(self.config, SCHEDULE_FRACTIONS),
        }
        if self.pose_optimizer is not None:
            state["pose_optimizer"] = self.pose_optimizer.state_dict()
        if self.appearance is not None:
            state["appearance_optimizer"] = self.appearance.optimizer.state_dict()
        return state

    def load_training_state(self, state: dict) -> None:
        self.optimizer.load_state_dict(state["optimizer"])
        if self.pose_optimizer is not None:
            self.pose_optimizer.load_state_dict(state["pose_optimizer"])
        if self.appearance is not None:
            self.appearance.optimizer.load_state_dict(state["appearance_optimizer"])
        self.densify_state = {
            k: v.to(self.params["means"].device) for k, v in state["densify"].items()
        }
        if "schedules" in state:  # as re-planned (`replan`) by the step it was saved at
            self.config = replace(self.config, **state["schedules"])
            self.strategy = densify_strategy(self.config, self._unbounded)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Resize the Gaussian tensors to the saved count first (densification changes it), then
        load; the optimizer and accumulators restart for the new tensors (see
        `load_training_state` to restore them)."""
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
# scenes (fox's 13.6k sfm Gaussians 6-14 % faster than that, lego-200's 4k random ones 9 %
# slower), so either sits well inside the prior's tolerance.
RESOLUTION = ResolutionPolicy(
    pixels_per_s=450e3,
    pixels_per_step=0.0,
    min_epochs=30.0,
    max_side=1600,
    step_overhead_s=0.05,
    step_pixels_per_s=1.0e6,
    probe_overhead_s=0.0082,
    probe_pixels_per_s=1.9e6,
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
