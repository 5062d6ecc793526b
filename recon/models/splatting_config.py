"""`--method 3dgs`'s flat config (one CLI flag per field) and its presets: the reference's
settings (Kerbl et al. 2023), the CPU's fast ones and the GPU's, and how the step schedules of
a preset scale into a planned run (`schedule_fractions`)."""

from __future__ import annotations

from dataclasses import dataclass

from recon.gaussians import densify, mcmc
from recon.options import opt

# A capture whose camera extent is below this fraction of the median depth of its SfM points
# is seen from a small baseline (all cameras looking one way: a forward-facing capture)
FORWARD_FACING_RATIO = 0.5
EXTENT_RULES = ("auto", "cameras", "depth")


# How late in a run of `schedule_steps` steps each step schedule may end (`fit_schedules`,
# schedule_fit "tuned": the fast preset's; "reference" scales the config's own schedules,
# `schedule_fractions`): with the fast preset and a 1,600-step plan: lr_decay_steps 1,600, densify_stop 1,120,
# opacity_reset_interval 560, sh_degree_interval 320. Densifying until 0.7 of the run with the
# means' rate decayed over all of it leaves the last third to refine what densification made;
# the lego-tuned steps or everything shrunk by one factor densify too little on a real capture
# (bench/results/3dgs_real_capture.md).
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
    average_window: float = opt(
        0.0,
        "from the step densification stops on, keep an exponential moving average of the parameters over this fraction of the run's planned steps and end the run as it (0 = off: the run ends as its last step, as the reference)",
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
        # growing long before a CPU run ends, the run's few steps leaving the view-space
        # gradients small (bench/results/3dgs_c2f_ab.md)
        "densify_grad_threshold": 0.00015,
        # twice the reference's rates for the means, scales and colours (opacity and rotations
        # unchanged): they are tuned for 30 k steps and a CPU run makes 1.5-8 k; four times
        # overshoots (bench/results/3dgs_lr_scale.md)
        "lr_means": 0.00032,
        "lr_means_final": 0.0000032,
        "lr_scales": 0.01,
        "lr_sh_dc": 0.005,
        "lr_sh_rest": 0.00025,
        # and on real captures all but the means' (which decay 100x over the run) anneal to a
        # tenth over the run's second half, in place of the reference's constant rates: one
        # image a step at these rates leaves the opacities and scales jittering (a synthetic
        # scene's exact photos do not: auto; see anneal_factor)
        "lr_anneal": -1.0,
        # at these rates the scene fits a wrong camera pose sooner: a shorter pose probation
        # (bench/results/3dgs_pose_refine.md; see pose_probation_passes above)
        "pose_probation_passes": 4,
        # no coarse-to-fine: what it saves in the first steps' time it loses again to larger
        # Gaussians (bench/results/3dgs_c2f_ab.md)
        "appearance": "auto",
        # AbsGS densification on real captures only: it splits textured regions whose signed
        # gradients cancel, which a synthetic scene's clean photos do not need
        # (bench/results/3dgs_absgrad.md)
        "densify_abs_grad": "auto",
        # the run ends as the moving average of its last 5 % of steps: fox-real's 30-minute
        # plan (6,560 steps, one view each) ended at 33.19 dB as its last step and at 33.61 as
        # the average (windows of 2, 5 and 10 % and the uniform mean since densification:
        # 33.59-33.62; bench/results/2026-11-29-3dgs-average.md)
        "average_window": 0.05,
    },
}
# What `--preset auto` means on a GPU: the reference's settings and schedules (scaled into the
# planned steps), plus what a real capture needs that the reference's synthetic and curated
# scenes did not: per-photo exposure compensation, AbsGS densification and the annealed rates,
# each "auto" (real captures only: a synthetic scene trains as with "paper";
# bench/results/2026-11-28-3dgs-gpu-preset.md); and the fast preset's parameter average.
PRESETS["gpu"] = {
    **PRESETS["paper"],
    "appearance": "auto",
    "densify_abs_grad": "auto",
    "lr_anneal": -1.0,
    "average_window": PRESETS["fast"]["average_window"],  # measured on a CPU only
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
