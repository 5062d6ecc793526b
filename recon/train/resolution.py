"""The working resolution of a training run: the pyramid level (an integer downscale K of the
sfm images) chosen from the scene, the method and the budget, or set by the user.

A CPU cannot fit a 12-megapixel photo collection in minutes: the training images must be small
enough that the budget covers enough passes over them. With a time budget T, a method that gets
through `pixels_per_s` training pixels a second (scaled by threads / 2, the measured setting)
makes T * pixels_per_s / (C * W_K * H_K) passes ("epochs") over C views of W_K x H_K pixels; a
--steps run makes steps * pixels_per_step of them. The chosen level is the finest one that still
gives `min_epochs`, never finer than `max_side` on the longer side and never coarser than
`MIN_SIDE` (INRIA's 3DGS and nerfstudio cap photos at ~1.6k px in the same spirit, with no
budget in the rule).
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass

import torch

from recon.models.base import MethodSpec, ResolutionPolicy
from recon.train.config import TrainConfig
from recon.workspace.scene import Scene, level_size

MIN_SIDE = 128  # the automatic choice never trains on a longer side below this
MEASURED_THREADS = 2  # the CPU throughputs of ResolutionPolicy were measured at 2 threads


@dataclass(frozen=True)
class WorkingResolution:
    downscale: int  # pyramid level: the sfm images downscaled by this integer
    width: int
    height: int
    source: str  # auto | max_side | downscale (which rule or option decided)
    reason: str  # one sentence for the log and run.json

    def to_json(self) -> dict:
        return asdict(self)


def epochs_at(
    width: int,
    height: int,
    n_views: int,
    policy: ResolutionPolicy,
    time_budget_s: float,
    steps: int,
    threads: int,
) -> float | None:
    """Passes over every training pixel the budget allows at this size. Only the bounds that
    depend on the size count: a --steps run of a method that trains on one whole image per step
    makes steps / n_views passes at any size. None: no such bound."""
    pixels = n_views * width * height
    bounds = []
    if time_budget_s > 0:
        bounds.append(time_budget_s * policy.pixels_per_s * threads / MEASURED_THREADS / pixels)
    if steps > 0 and policy.pixels_per_step > 0:
        bounds.append(steps * policy.pixels_per_step / pixels)
    return min(bounds) if bounds else None


def planned_steps(
    width: int,
    height: int,
    policy: ResolutionPolicy,
    time_budget_s: float,
    steps: int,
    threads: int,
    cpu: bool = True,
) -> int:
    """The steps a run at width x height is expected to make: --steps, or what the time budget
    buys on a CPU at the policy's step time, the smaller of the two; 0 when nothing bounds the
    run. A step costs step_overhead_s + P / step_pixels_per_s seconds on 2 threads (P =
    pixels_per_step, or one image), scaled by 2 / threads. Only an estimate (a 3DGS step slows
    as Gaussians are added and is faster at the coarse levels): schedules laid out over it need
    not end exactly at the last step.
    Example: 600 s of 3dgs at 269 x 478 on 2 threads, 50 ms + 1 us per pixel a step ->
    600 / (0.05 + 128582 / 1e6) = 3359 steps (the fox-real benchmark made 3,642)."""
    bounds = [steps] if steps > 0 else []
    if time_budget_s > 0 and cpu:
        pixels = policy.pixels_per_step or width * height
        step_s = policy.step_overhead_s + pixels / (policy.step_pixels_per_s or policy.pixels_per_s)
        bounds.append(int(time_budget_s * threads / MEASURED_THREADS / step_s))
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
    threads: int = MEASURED_THREADS,
    cpu: bool = True,
    max_side: int = 0,
    downscale: int = 0,
) -> WorkingResolution:
    """The working resolution for C = n_views training images of width x height (the sfm size).

    `downscale` / `max_side` (the user's options) override the rule. On a CPU with a time
    budget: the finest K (coarsest at the `MIN_SIDE` floor) whose `epochs_at` reaches
    `policy.min_epochs`, capped at `policy.max_side`. Elsewhere (no budget, or a GPU, where
    the CPU throughput says nothing) the cap alone decides.
    Example: fox, 58 views of 1076 x 1913, 3dgs (350k px/s, 30 epochs), 600 s on 2 threads ->
    K = 5 (215 x 382: 44 epochs; K = 4 would give 28).
    """

    def result(k: int, source: str, reason: str) -> WorkingResolution:
        w, h = level_size(width, height, k)
        return WorkingResolution(k, w, h, source, reason)

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
    if not cpu or epochs_at(width, height, n_views, policy, time_budget_s, steps, threads) is None:
        why = (
            "no budget that depends on the image size"
            if cpu
            else "no measured throughput on this device"
        )
        return result(k_cap, "auto", f"{why}: {cap_note}")
    k_floor = max(k_cap, downscale_for_max_side(width, height, MIN_SIDE))
    k = k_cap
    while (
        k < k_floor
        and epochs_at(*level_size(width, height, k), n_views, policy, time_budget_s, steps, threads)
        < policy.min_epochs
    ):
        k += 1
    epochs = epochs_at(
        *level_size(width, height, k), n_views, policy, time_budget_s, steps, threads
    )
    budget = " and ".join(
        x
        for x in (
            f"{time_budget_s:g} s" if time_budget_s > 0 else "",
            f"{steps} steps" if steps > 0 else "",
        )
        if x
    )
    why = (
        f"{budget} at ~{policy.pixels_per_s * threads / MEASURED_THREADS / 1e3:.0f}k px/s give "
        f"{epochs:.0f} passes over the {n_views} training views at this size "
        f"(>= {policy.min_epochs:g} wanted)"
    )
    if k > k_cap:
        finer = epochs_at(
            *level_size(width, height, k - 1), n_views, policy, time_budget_s, steps, threads
        )
        why += (
            f"; 1/{k - 1} would give {finer:.0f}"
            if k > 2
            else f"; full size would give {finer:.0f}"
        )
    if epochs < policy.min_epochs:
        why += f"; not coarser than {MIN_SIDE} px on the longer side"
    elif k == k_cap and k_cap > 1:
        why += f"; {cap_note}"
    return result(k, "auto", why)


# ---- the rule applied to a workspace's scene and a run --------------------------------------
def working_resolution(
    scene: Scene,
    spec: MethodSpec,
    cfg: TrainConfig,
    device: torch.device,
) -> WorkingResolution:
    """The pyramid level this run trains at (see `recon.train.resolution`)."""
    width, height = scene.image_size("train")
    return choose_resolution(
        width,
        height,
        len(scene.split("train")),
        spec.resolution,
        cfg.time_budget_s,
        cfg.steps,
        _threads(cfg),
        device.type == "cpu",
        cfg.max_side,
        cfg.downscale,
    )


def _threads(cfg: TrainConfig) -> int:
    return cfg.threads or torch.get_num_threads() or MEASURED_THREADS


def plan_schedules(
    method_cfg, spec: MethodSpec, cfg: TrainConfig, res: WorkingResolution, device: torch.device
):
    """A method whose config has a `schedule_steps` field left at 0 gets the run's planned step
    count there (`resolution.planned_steps`), to lay its step-based schedules out over the run
    it will actually have. Returns the (possibly) updated config."""
    if getattr(method_cfg, "schedule_steps", None) != 0:
        return method_cfg
    plan = planned_steps(
        res.width,
        res.height,
        spec.resolution,
        cfg.time_budget_s,
        cfg.steps,
        _threads(cfg),
        device.type == "cpu",
    )
    return dataclasses.replace(method_cfg, schedule_steps=plan) if plan else method_cfg


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
