"""The rules `--method 3dgs` applies to its config and scene, as pure functions: the loss, the
scene extent the means' rate and the densification thresholds are measured in, the learning-rate
schedules, the view order, and what each "auto" option resolves to on a bounded or an
unbounded scene (`recon.models.splatting` calls them; tests check each on its own)."""

from __future__ import annotations

import torch
from torch import Tensor

from recon.cameras import Cameras
from recon.gaussians import densify, mcmc
from recon.gaussians.ssim import ssim
from recon.gaussians.strategy import Strategy
from recon.models.base import SceneInfo
from recon.models.schedules import (
    exp_decay_lr,
)
from recon.models.splatting_config import EXTENT_RULES, FORWARD_FACING_RATIO, GaussiansConfig
from recon.options import on_off_auto


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
    scenes: a real capture's photos disagree a little (exposure, motion), and constant rates
    keep the opacities and scales chasing each photo; a synthetic scene's exact photos keep
    improving at constant rates (bench/results/3dgs_lr_anneal.md)."""
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
    """prune_contribution, or with -1 (auto) 0.5 for bounded scenes and 0 for unbounded ones:
    a bounded scene keeps its picture with half the Gaussians, a real capture's short runs
    leave too few steps to refill the background (bench/results/3dgs_prune_contribution.md).
    With densify_mode mcmc, auto is 0: max_gaussians is already the budget."""
    if config.prune_contribution != -1.0:
        return config.prune_contribution
    return 0.0 if scene.unbounded or uses_mcmc(config, bool(scene.unbounded)) else 0.5


def uses_antialiasing(config: GaussiansConfig, unbounded: bool) -> bool:
    """on | off, or auto: on for unbounded captures (real photos: at equal steps on fox-real it
    scores higher at the training size and, with the footprint filter, at the photos' size no
    worse than the training-size render upsampled, where the plain model is worse), off for
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
    """on | off, or auto: on for unbounded captures, whose textured regions have view-space
    gradients that cancel in sign; a synthetic scene does better without
    (bench/results/3dgs_absgrad.md; its threshold 0.0006: lower grows Gaussians that cost
    steps)."""
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
