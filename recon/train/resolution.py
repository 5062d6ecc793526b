"""The working resolution of a training run: the pyramid level (an integer downscale K of the
sfm images) chosen from the scene, the method and the budget, or set by the user.

A CPU cannot fit a 12-megapixel photo collection in minutes: the training images must be small
enough that the budget covers enough passes over them. With a time budget T, a method that gets
through R training pixels a second (`ResolutionPolicy.pixels_per_s` at the device's measured
`Speed`, `recon.train.throughput`) makes T * R / (C * W_K * H_K) passes ("epochs") over C views
of W_K x H_K pixels; a --steps run makes steps * pixels_per_step of them. The chosen level is
the finest one that still gives `min_epochs`, never finer than `max_side` on the longer side and
never coarser than `MIN_SIDE` (INRIA's 3DGS and nerfstudio cap photos at ~1.6k px in the same
spirit, with no budget in the rule). A finer level than that is taken where the photos hold
detail there (`photo_detail`: the level against the next coarser one upsampled, under
`DETAIL_DB`) and `policy.detail_views` passes are still made: training finer pays only in what
a finer render shows, which smooth photos (a phone's, fox's) lack and crisp ones have.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np
import torch

from recon.io.images import resize_area
from recon.models.base import MethodSpec, ResolutionPolicy, SceneInfo, TrainData
from recon.train.config import TrainConfig
from recon.train.throughput import (
    PROBE_SIDES,
    PROBE_TRIES,
    PROBE_VIEWS,
    REFERENCE,
    ProbeSample,
    Speed,
    fastest,
    pixels_per_s,
    prior_speed,
    run_probe,
    settled_speed,
    step_seconds,
)
from recon.workspace import Workspace
from recon.workspace.scene import Scene, level_size, load_images_and_alpha

MIN_SIDE = 128  # the automatic choice never trains on a longer side below this
# A pyramid level whose photos its next coarser level, upsampled (bicubic), reproduces to less
# than this PSNR holds detail a render at the photos' size shows (fox's phone photos: 42 dB at
# 1/2 against 1/3; spiral-300's crisp texture: 29 dB at full size against 1/2; llff_flower 38)
DETAIL_DB = 35.0
DETAIL_VIEWS = 4  # training views the photos' detail is measured on (evenly spaced)


@dataclass(frozen=True)
class WorkingResolution:
    downscale: int  # pyramid level: the sfm images downscaled by this integer
    width: int
    height: int
    source: str  # auto | max_side | downscale (which rule or option decided)
    reason: str  # one sentence for the log and run.json

    def to_json(self) -> dict:
        return asdict(self)


def policy_step_pixels(width: int, height: int, policy: ResolutionPolicy) -> float:
    """The pixels a training step takes in the policy's figures: its pixels_per_step, or one
    whole image (`Model.step_pixels` is what a model says of its own next step)."""
    return policy.pixels_per_step or width * height


def counted_views(n_views: int, policy: ResolutionPolicy) -> int:
    """The views whose passes the rule counts: all n_views, or at most policy.epoch_views."""
    return min(n_views, policy.epoch_views) if policy.epoch_views > 0 else n_views


def epochs_at(
    width: int,
    height: int,
    n_views: int,
    policy: ResolutionPolicy,
    time_budget_s: float,
    steps: int,
    speed: Speed = REFERENCE,
) -> float | None:
    """Passes over every training pixel the budget allows at this size, at the device's
    `speed` (`throughput.pixels_per_s`). Only the bounds that depend on the size count: a
    --steps run of a method that trains on one whole image per step makes steps / n_views
    passes at any size. None: no such bound."""
    pixels = counted_views(n_views, policy) * width * height
    bounds = []
    if time_budget_s > 0:
        rate = pixels_per_s(policy, policy_step_pixels(width, height, policy), speed)
        bounds.append(time_budget_s * rate / pixels)
    if steps > 0 and policy.pixels_per_step > 0:
        bounds.append(steps * policy.pixels_per_step / pixels)
    return min(bounds) if bounds else None


def planned_steps(
    width: int,
    height: int,
    policy: ResolutionPolicy,
    time_budget_s: float,
    steps: int,
    speed: Speed = REFERENCE,
) -> int:
    """The steps a run at width x height is expected to make: --steps, or what the time budget
    buys at the policy's step time on the device (`throughput.step_seconds`), the smaller of
    the two; 0 when nothing bounds the run. Only an estimate (a 3DGS step slows as Gaussians
    are added and is faster at the coarse levels): schedules laid out over it need not end
    exactly at the last step, and the loop re-plans them from the step rate it gets
    (`recon.train.replan`).
    Example: 600 s of 3dgs at 269 x 478 at the reference speed, 50 ms + 1 us per pixel a step
    -> 600 / (0.05 + 128582 / 1e6) = 3359 steps (the fox-real benchmark made 3,642)."""
    bounds = [steps] if steps > 0 else []
    if time_budget_s > 0:
        step_s = step_seconds(policy, policy_step_pixels(width, height, policy), speed)
        bounds.append(int(time_budget_s / step_s))
    return min(bounds) if bounds else 0


def downscale_for_max_side(width: int, height: int, max_side: int) -> int:
    """The smallest K whose level has a longer side <= max_side (1 if the images already fit)."""
    k = 1
    while max(level_size(width, height, k)) > max_side and max(level_size(width, height, k)) > 1:
        k += 1
    return k


def choose_resolution(
    width: int,
    height: int,
    n_views: int,
    policy: ResolutionPolicy,
    time_budget_s: float = 0.0,
    steps: int = 0,
    speed: Speed = REFERENCE,
    max_side: int = 0,
    downscale: int = 0,
    detail: Callable[[int], float] | None = None,
) -> WorkingResolution:
    """The working resolution for C = n_views training images of width x height (the sfm size).

    `downscale` / `max_side` (the user's options) override the rule. With a time budget: the
    finest K (coarsest at the `MIN_SIDE` floor) whose `epochs_at` at the device's `speed`
    reaches `policy.min_epochs`, capped at `policy.max_side`. Without one the cap alone
    decides.
    Example: fox, 58 views of 1076 x 1913, 3dgs (350k px/s, 30 epochs), 600 s at the reference
    speed -> K = 5 (215 x 382: 44 epochs; K = 4 would give 28).
    With `detail` (level -> `photo_detail` of the photos there) and a policy's `detail_views`,
    a finer level is taken while its photos hold detail (under DETAIL_DB) and the passes
    counted over detail_views views still reach min_epochs.
    """

    def result(k: int, source: str, reason: str) -> WorkingResolution:
        w, h = level_size(width, height, k)
        return WorkingResolution(k, w, h, source, reason)

    def epochs(k: int) -> float | None:
        return epochs_at(
            *level_size(width, height, k), n_views, policy, time_budget_s, steps, speed
        )

    if downscale:
        return result(downscale, "downscale", f"--downscale {downscale} was given")
    if max_side:
        return result(
            downscale_for_max_side(width, height, max_side),
            "max_side",
            f"--max-side {max_side} was given",
        )
    k_cap = downscale_for_max_side(width, height, policy.max_side)
    cap_note = f"the longer side is capped at {policy.max_side} px"
    if epochs(k_cap) is None:
        return result(k_cap, "auto", f"no budget that depends on the image size: {cap_note}")
    k_floor = max(k_cap, downscale_for_max_side(width, height, MIN_SIDE))
    k = k_cap
    while k < k_floor and epochs(k) < policy.min_epochs:
        k += 1
    budget = " and ".join(
        x
        for x in (
            f"{time_budget_s:g} s" if time_budget_s > 0 else "",
            f"{steps} steps" if steps > 0 else "",
        )
        if x
    )
    rate = pixels_per_s(policy, policy_step_pixels(*level_size(width, height, k), policy), speed)
    counted = counted_views(n_views, policy)
    views = f"{n_views}" if counted == n_views else f"{counted} (of {n_views})"
    why = (
        f"{budget} at ~{rate / 1e3:.0f}k px/s give {epochs(k):.0f} passes over {views} "
        f"training views at this size (>= {policy.min_epochs:g} wanted)"
    )
    if detail is not None and policy.detail_views > 0 and epochs(k) >= policy.min_epochs:
        k_passes, fewer, db = k, dataclasses.replace(policy, epoch_views=policy.detail_views), None
        while k > k_cap:
            w, h = level_size(width, height, k - 1)
            if epochs_at(w, h, n_views, fewer, time_budget_s, steps, speed) < policy.min_epochs:
                break
            finer_db = detail(k - 1)
            if finer_db >= DETAIL_DB:
                break
            k, db = k - 1, finer_db
        if k < k_passes:
            w, h = level_size(width, height, k)
            rate = pixels_per_s(policy, policy_step_pixels(w, h, policy), speed)
            passes = epochs_at(w, h, n_views, fewer, time_budget_s, steps, speed)
            level = f"1/{k_passes}" if k_passes > 1 else "full size"
            return result(
                k,
                "auto",
                f"{budget} at ~{rate / 1e3:.0f}k px/s give {passes:.0f} passes over "
                f"{counted_views(n_views, fewer)} (of {n_views}) training views at this size "
                f"(>= {policy.min_epochs:g} wanted over at most {policy.detail_views} views: "
                f"its photos hold detail the next coarser level lacks, {db:.1f} dB against it "
                f"upsampled, under {DETAIL_DB:g}); over {counted} views it would give "
                f"{epochs(k):.0f} and {level} would be chosen",
            )
    if k > k_cap:
        finer = epochs(k - 1)
        why += (
            f"; 1/{k - 1} would give {finer:.0f}"
            if k > 2
            else f"; full size would give {finer:.0f}"
        )
    if epochs(k) < policy.min_epochs:
        why += f"; not coarser than {MIN_SIDE} px on the longer side"
    elif k == k_cap and k_cap > 1:
        why += f"; {cap_note}"
    return result(k, "auto", why)


def photo_detail(photos: np.ndarray, k: int) -> float:
    """How much of the photos pyramid level `k` holds beyond level k + 1: the PSNR of the level
    (each photo area-downsampled by k, as `WS/images_<k>/`) against level k + 1 upsampled to
    its size (bicubic), over photos (V, H, W, 3) in [0, 1] at the sfm size; at most 100 dB.
    Limiting cases: a flat colour -> 100; pixel-wide stripes at k = 1 -> a few dB."""
    height, width = photos.shape[1:3]
    fine = np.stack([resize_area(p, *level_size(width, height, k)) for p in photos])
    coarse = np.stack([resize_area(p, *level_size(width, height, k + 1)) for p in photos])
    up = torch.nn.functional.interpolate(
        torch.from_numpy(coarse).permute(0, 3, 1, 2).double(),
        size=fine.shape[1:3],
        mode="bicubic",
        align_corners=False,
    ).clamp(0, 1)
    mse = ((up.permute(0, 2, 3, 1) - torch.from_numpy(fine).double()) ** 2).mean().item()
    return min(100.0, 10 * math.log10(1 / mse)) if mse > 0 else 100.0


def scene_photo_detail(ws: Workspace, scene: Scene) -> Callable[[int], float]:
    """`photo_detail` of DETAIL_VIEWS evenly spaced training photos, level -> dB (read once,
    at the sfm size, when first asked)."""
    cache: dict = {}

    def at(k: int) -> float:
        if "photos" not in cache:
            idx = scene.split("train")
            picks = np.linspace(0, len(idx) - 1, min(DETAIL_VIEWS, len(idx))).round().astype(int)
            views = [idx[i] for i in sorted(set(picks))]
            cache["photos"] = load_images_and_alpha(ws, scene, views, 1)[0].numpy()
        if k not in cache:
            cache[k] = photo_detail(cache["photos"], k)
        return cache[k]

    return at


# ---- the rule applied to a workspace's scene and a run --------------------------------------
def working_resolution(
    scene: Scene,
    spec: MethodSpec,
    cfg: TrainConfig,
    speed: Speed,
    detail: Callable[[int], float] | None = None,
) -> WorkingResolution:
    """The pyramid level this run trains at (see `recon.train.resolution`); `detail`: level ->
    `photo_detail` of the scene's photos (`scene_photo_detail`)."""
    width, height = scene.image_size("train")
    return choose_resolution(
        width,
        height,
        len(scene.split("train")),
        spec.resolution,
        cfg.time_budget_s,
        cfg.steps,
        speed,
        cfg.max_side,
        cfg.downscale,
        detail,
    )


def threads(cfg: TrainConfig) -> int:
    """The run's CPU threads (--threads, or torch's)."""
    return cfg.threads or torch.get_num_threads() or 1


def plans_schedules(spec: MethodSpec, method_cfg) -> bool:
    """The method plans its schedules (`MethodSpec.plans_schedules`) and this run's config
    leaves `schedule_steps` at 0 for the run to fill in (not given with --set)."""
    return spec.plans_schedules and method_cfg.schedule_steps == 0


def plan_schedules(method_cfg, spec: MethodSpec, cfg: TrainConfig, res: WorkingResolution, speed):
    """A method that plans its schedules, its config's `schedule_steps` left at 0, gets the
    run's planned step count there (`resolution.planned_steps` at the device's `speed`), to lay its step-based
    schedules out over the run it will actually have. Returns the (possibly) updated config."""
    if not plans_schedules(spec, method_cfg):
        return method_cfg
    plan = planned_steps(
        res.width, res.height, spec.resolution, cfg.time_budget_s, cfg.steps, speed
    )
    return dataclasses.replace(method_cfg, schedule_steps=plan) if plan else method_cfg


def probe_levels(width: int, height: int, policy: ResolutionPolicy) -> list[int]:
    """The pyramid levels the throughput probe trains at, coarse to fine: the coarsest of
    `PROBE_SIDES` for a method of a fixed pixel batch (a step costs the same at any level), each
    of them for a method of one whole image a step (two sizes separate a step's fixed and
    per-pixel costs). Example: 1076 x 1913 -> [15, 8] (71 x 127 and 134 x 239); 200 x 200 ->
    [2, 1]; ngp -> [15]."""
    sides = PROBE_SIDES if policy.pixels_per_step <= 0 else PROBE_SIDES[:1]
    return sorted({downscale_for_max_side(width, height, s) for s in sides}, reverse=True)


def probe_scene(info: SceneInfo, max_points: int) -> SceneInfo:
    """The scene the probe's throw-away model is built from: `info` with at most `max_points`
    of its sfm points, evenly spaced through them (0: all). Example: 31,921 points, 8,000 ->
    points 0, 4, 8, ... 31,920 (every 3.99th); 7,939 points -> all of them."""
    n = 0 if info.points is None else len(info.points)
    if max_points <= 0 or n <= max_points:
        return info
    keep = torch.linspace(0, n - 1, max_points, device=info.points.device).round().long()
    colors = None if info.point_colors is None else info.point_colors[keep]
    return dataclasses.replace(info, points=info.points[keep], point_colors=colors)


def needs_speed(cfg: TrainConfig, spec: MethodSpec, method_cfg) -> bool:
    """A new run's level or step plan depends on the device's speed: a time budget, and the
    level left to the rule or step schedules to plan."""
    auto_level = not (cfg.downscale or cfg.max_side)
    return cfg.time_budget_s > 0 and (auto_level or plans_schedules(spec, method_cfg))


def measure_speed(
    ws: Workspace, scene: Scene, spec: MethodSpec, method_cfg, cfg: TrainConfig, device
) -> tuple[Speed, dict]:
    """The device's `Speed` for this run, and what was measured (for run.json): the probe
    (`throughput.run_probe`) of a throw-away model built from the run's config (and at most
    `policy.probe_points` sfm points: `probe_scene`) on `PROBE_VIEWS` training views, settled
    against the prior on a CPU (`throughput.settled_speed`); the prior where nothing depends on it or the method has no
    reference probe (off a CPU, the reference machine's figures)."""
    cpu = device.type == "cpu"
    prior = prior_speed(threads(cfg)) if cpu else REFERENCE
    policy = spec.resolution
    if not needs_speed(cfg, spec, method_cfg) or policy.probe_pixels_per_s <= 0:
        return prior, {"probe": None}
    idx = scene.split("train")
    views = [
        idx[i] for i in sorted(set(np.linspace(0, len(idx) - 1, PROBE_VIEWS).round().astype(int)))
    ]
    rgb, alpha = load_images_and_alpha(ws, scene, views, 1)
    data = TrainData(
        rgb.to(device),
        scene.cameras(views, device, 1),
        None if alpha is None else alpha.to(device),
    )
    levels = probe_levels(*scene.image_size("train"), policy)
    model = spec.build(method_cfg, probe_scene(scene.info, policy.probe_points)).to(device)
    samples: list[ProbeSample] = []
    for tries in range(1, PROBE_TRIES + 1):
        samples = fastest(samples, run_probe(model, data, levels))
        speed = settled_speed(policy, samples, prior if cpu else None)
        if speed.source == "prior" or not cpu:  # contention is a CPU's
            break
    probe = {"levels": levels, "samples": [asdict(s) for s in samples], "tries": tries}
    return speed, {"probe": probe}


def trained_resolution(run_doc: dict, scene: Scene) -> WorkingResolution:
    """The working resolution recorded in a run.json (runs from before working resolutions
    existed trained on the sfm images themselves)."""
    saved = run_doc.get("resolution", {}).get("working")
    if saved:
        return WorkingResolution(**saved)
    return WorkingResolution(
        1, *scene.image_size("train"), "downscale", "recorded before levels existed"
    )


def output_levels(
    scene: Scene,
    run_doc: dict,
    max_side: int = 0,
    downscale: int = 0,
) -> tuple[int, int]:
    """(output level, render level) for `recon eval` / `recon render` of a run: the output is
    at `downscale`, or the level that fits `max_side`, or by default the run's training level;
    it is rendered at the finer of the output and training levels (a coarser output is then
    area-downsampled from the render, like the photos of that level)."""
    trained = trained_resolution(run_doc, scene).downscale
    if downscale:
        out = downscale
    elif max_side:
        out = downscale_for_max_side(*scene.image_size("train"), max_side)
    else:
        out = trained
    return out, min(out, trained)


def eval_downscale(scene: Scene, train_downscale: int, max_side: int) -> int:
    """The level of the periodic held-out PSNR: the training level, or coarser so that the
    longer side is at most `max_side` (a few small renders, cheap inside the time budget)."""
    width, height = scene.image_size("train")
    return max(train_downscale, downscale_for_max_side(width, height, max_side) if max_side else 1)
