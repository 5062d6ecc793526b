"""The training loop: steps, held-out PSNR on a wall-clock schedule, checkpoints, stopping.

Two clocks: `wall_s` counts training steps only (the speed-vs-error curve measures the method,
not our bookkeeping), `elapsed_s` everything the run spends (setup, evaluations, checkpoints).
The time budget bounds `elapsed_s`, keeping the final evaluation's time in reserve, so
`recon train --time-budget T` returns after about T seconds.

The reserve is the last evaluation's cost. A model's renders can get much cheaper as it trains
(ngp on an unbounded capture: the occupancy grid empties and early termination drops most
samples, a held-out view 22 s early on, 5 s late), and later periodic evaluations may be skipped
(`eval_due`'s cap), so a reserve measured long ago is re-measured on one held-out view when the
budget is about to run out (`RESERVE_STALE_FRACTION`): the fox-real ngp runs had stopped ~50 s
early on the cost of their first evaluation.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch

from recon.cameras import Cameras
from recon.io.images import resize_area
from recon.metrics.image import training_psnr
from recon.models.base import Model, TrainData
from recon.train.config import TrainConfig
from recon.train.replan import Replanner
from recon.train.trainer import Trainer


@dataclass
class LoopState:
    step: int = 0
    wall_s: float = 0.0  # training time so far (excludes eval and checkpoints)
    best_psnr: float = -math.inf
    evals_since_best: int = 0
    last_eval_wall: float = 0.0  # the first evaluation comes after eval_every_s of training
    last_psnr_wall: float = 0.0  # wall_s of the last evaluation that gave a PSNR (not deferred)
    last_ckpt_wall: float = 0.0
    elapsed_s: float = 0.0  # wall time of the run so far, evaluations and checkpoints included
    eval_cost_s: float = 0.0  # how long the last held-out evaluation took (or a re-measure)
    eval_total_s: float = 0.0  # how long all held-out evaluations took
    eval_cost_wall: float = 0.0  # wall_s when eval_cost_s was measured
    schedule_steps: int = 0  # the run length the model's schedules were last re-planned to
    # (for the log and run.json; the model's checkpointed training state keeps the schedules)


@torch.no_grad()
def heldout_psnr(
    model: Model,
    cameras: Cameras,
    images: torch.Tensor,
    interrupted: Callable[[], bool] = lambda: False,
    go_on: Callable[[int, float], bool] | None = None,
) -> float | None:
    """Mean PSNR (dB) of the model's renders of held-out views against the photos (C, h, w, 3).
    Cameras finer than the photos are rendered at their own size and area-downsampled to the
    photos' (as the photos of a coarser pyramid level are made). Raises KeyboardInterrupt
    between two views once `interrupted()` (Ctrl-C / SIGTERM never waits for a whole
    evaluation). `go_on(views done, seconds so far)`, asked between two views, may abandon the
    evaluation: then None."""
    was_training = model.training
    model.eval()
    psnrs = []
    height, width = images.shape[1:3]
    t0 = time.perf_counter()
    try:
        for i in range(len(cameras)):
            if interrupted():
                raise KeyboardInterrupt
            if i and go_on is not None and not go_on(i, time.perf_counter() - t0):
                return None
            rgb = model.render(cameras[i])["rgb"].clamp(0, 1)
            if rgb.shape[:2] != (height, width):
                small = resize_area(rgb.float().cpu().numpy(), width, height)
                rgb = torch.from_numpy(small).to(rgb.device)
            mse = torch.mean((rgb - images[i].to(rgb.device)) ** 2).item()
            psnrs.append(training_psnr(mse))
    finally:
        model.train(was_training)
    return float(sum(psnrs) / len(psnrs))


RESERVE_STALE_FRACTION = 0.1  # re-measure a reserve older than this share of the budget


def should_stop(cfg: TrainConfig, st: LoopState) -> str | None:
    """The reason to stop now, or None. The time budget keeps the last evaluation's duration in
    reserve for the final one."""
    if cfg.steps and st.step >= cfg.steps:
        return "steps"
    if cfg.time_budget_s and st.elapsed_s + st.eval_cost_s >= cfg.time_budget_s:
        return "time_budget"
    if cfg.patience and st.evals_since_best >= cfg.patience:
        return "converged"
    return None


def report_progress(progress, cfg: TrainConfig, st: LoopState, stats: dict) -> None:
    """One progress update after a step: against the step count with --steps, else against the
    time budget in seconds (so the bar's ETA is the time left), with the step, the training
    PSNR and the best held-out PSNR so far."""
    info = {
        "psnr": stats.get("psnr"),
        "test_psnr": None if st.best_psnr == -math.inf else round(st.best_psnr, 2),
    }
    if cfg.steps:
        progress("train steps", st.step, cfg.steps, **info)
    elif cfg.time_budget_s:
        done = min(int(st.elapsed_s), int(cfg.time_budget_s))
        progress("train s", done, int(cfg.time_budget_s), step=st.step, **info)
    else:
        progress("train steps", st.step, None, **info)


def run_loop(
    trainer: Trainer,
    data: TrainData,
    held_cams: Cameras | None,
    held_imgs: torch.Tensor | None,
    cfg: TrainConfig,
    st: LoopState,
    log: Callable[[dict], None],
    checkpoint: Callable[[LoopState], None],
    progress=None,
    interrupted: Callable[[], bool] = lambda: False,
) -> str:
    """Train until a stopping rule fires; returns the reason (steps | time_budget | converged).

    A step's stats may be 0-d tensors on the model's device (`Model.training_loss`): they are read
    (a host sync) only on the steps that are logged, every 10th and the first, and progress
    shows the last logged values. A non-finite loss is never trained on silently: read there,
    before a checkpoint and at the end, it raises FloatingPointError (the optimizer may already
    have written NaNs into the parameters) and the caller rolls back; so do non-finite
    parameters found before a checkpoint or at the end.
    """
    model = trainer.model
    model.train()
    clock = time.perf_counter()

    def tick() -> None:  # everything since the last tick counts towards elapsed_s
        nonlocal clock
        now = time.perf_counter()
        st.elapsed_s += now - clock
        clock = now

    def stop_reason() -> str | None:
        reason = should_stop(cfg, st)
        if reason == "time_budget" and held_cams is not None and reserve_stale(cfg, st):
            _remeasure_reserve(model, held_cams, held_imgs, st, interrupted)
            tick()
            reason = should_stop(cfg, st)
        return reason

    stats: dict = {}  # the last step's, as the trainer returned them
    logged: dict = {}  # the last logged step's, as Python numbers
    replanner = None
    if cfg.time_budget_s > 0:
        replanner = Replanner.starting_at(cfg.time_budget_s, st.step, st.wall_s, st.elapsed_s)
    while (reason := stop_reason()) is None:
        if interrupted():  # Ctrl-C / SIGTERM are honoured between steps, never inside one
            raise KeyboardInterrupt
        if held_cams is not None and eval_due(cfg, st, len(held_cams)):
            _evaluate(model, held_cams, held_imgs, cfg, st, log, interrupted)
            tick()
            if (reason := stop_reason()) is not None:
                break
        t0 = time.perf_counter()
        stats = trainer.step(data, st.step)
        st.wall_s += time.perf_counter() - t0
        st.step += 1
        tick()
        # The loss is read, and checked, only when it is logged: reading it every step would
        # wait for the device each step. A non-finite loss is then caught up to 9 steps late,
        # which the rollback to the last checkpoint covers (checkpoints check it first).
        if st.step % 10 == 0 or st.step == 1:
            logged = host_stats(stats)
            require_finite_loss(logged, st, log)
            log({"step": st.step, "wall_s": round(st.wall_s, 4), **_round(logged)})
        if replanner is not None and (
            projected := replanner.after_step(st.step, st.wall_s, st.elapsed_s, st.eval_cost_s)
        ):
            _replan(model, min(projected, cfg.steps or projected), st, log)
        if progress is not None:
            report_progress(progress, cfg, st, logged)
        if st.wall_s - st.last_ckpt_wall >= cfg.checkpoint_every_s:
            require_finite_loss(host_stats(stats), st, log)
            require_finite_parameters(model, st, log)
            checkpoint(st)
            st.last_ckpt_wall = st.wall_s
            tick()
    require_finite_loss(host_stats(stats), st, log)
    # the run ends as the average of its last iterates, where the model keeps one
    if averaged := trainer.use_average():
        log({"step": st.step, "wall_s": round(st.wall_s, 4), "event": "average", "steps": averaged})
    require_finite_parameters(model, st, log)
    if held_cams is not None and (averaged or st.last_psnr_wall < st.wall_s):
        _evaluate(model, held_cams, held_imgs, cfg, st, log, interrupted, final=True)
        tick()
    return reason


def _replan(model: Model, projected: int, st: LoopState, log: Callable[[dict], None]) -> None:
    """Have the model fit its step schedules into a run of `projected` steps (`recon.train.
    replan`); a change is noted in the loop state (for run.json) and logged."""
    followed = model.replan(projected, st.step)
    if followed:
        st.schedule_steps = followed
        log(
            {
                "step": st.step,
                "wall_s": round(st.wall_s, 4),
                "event": "replan",
                "schedule_steps": followed,
            }
        )


def host_stats(stats: dict) -> dict:
    """A step's stats with its 0-d tensors read as Python floats (a host sync on a GPU)."""
    return {k: float(v) if isinstance(v, torch.Tensor) else v for k, v in stats.items()}


def require_finite_loss(stats: dict, st: LoopState, log: Callable[[dict], None]) -> None:
    """Raise FloatingPointError if the step's "loss" (read by `host_stats`) is NaN/Inf."""
    loss = stats.get("loss", 0.0)
    if not math.isfinite(loss):
        log({"step": st.step, "wall_s": st.wall_s, "event": "non_finite_loss"})
        raise FloatingPointError(f"the loss became {loss} at step {st.step}")


def require_finite_parameters(model: Model, st: LoopState, log: Callable[[dict], None]) -> None:
    """Raise FloatingPointError if any parameter holds NaN/Inf. Checked before parameters are
    kept (a checkpoint, the final model): an update can overflow on a step whose loss was still
    finite, and no later loss would notice it."""
    bad = [name for name, p in model.named_parameters() if not bool(torch.isfinite(p).all())]
    if bad:
        log(
            {
                "step": st.step,
                "wall_s": st.wall_s,
                "event": "non_finite_parameters",
                "names": bad[:5],
            }
        )
        raise FloatingPointError(f"non-finite values in {', '.join(bad[:3])} after step {st.step}")


def eval_due(cfg: TrainConfig, st: LoopState, views: int = 1) -> bool:
    """A periodic evaluation of `views` held-out views is due every eval_every_s of training,
    unless its first view (at the last measured cost a view) would take the evaluations over
    eval_max_fraction of the wall time; the evaluation itself stops after any view past which
    the rest would (`within_eval_cap`). Example: 10 s evaluations of one view, fraction 0.1: at
    most one per 100 s of the run."""
    if st.wall_s - st.last_eval_wall < cfg.eval_every_s:
        return False
    return within_eval_cap(cfg, st, st.eval_cost_s / views)


def within_eval_cap(cfg: TrainConfig, st: LoopState, more_s: float) -> bool:
    """Whether `more_s` seconds more of evaluation keep all evaluations within
    eval_max_fraction of the run's wall time (0: no cap)."""
    if cfg.eval_max_fraction <= 0:
        return True
    return st.eval_total_s + more_s <= cfg.eval_max_fraction * (st.elapsed_s + more_s)


def reserve_stale(cfg: TrainConfig, st: LoopState) -> bool:
    """The reserve for the final evaluation was measured more than RESERVE_STALE_FRACTION of
    the budget ago (in training time), and holding it back is what stops the run."""
    return (
        st.eval_cost_s > 0
        and st.wall_s - st.eval_cost_wall > RESERVE_STALE_FRACTION * cfg.time_budget_s
        and st.elapsed_s < cfg.time_budget_s
    )


def _remeasure_reserve(model, cams, imgs, st: LoopState, interrupted) -> None:
    """The final evaluation's cost estimated anew: one held-out view's render, times the views
    (a full evaluation renders each once). Counted in elapsed_s like any evaluation."""
    t0 = time.perf_counter()
    heldout_psnr(model, cams[:1], imgs[:1], interrupted)
    one_view = time.perf_counter() - t0
    st.eval_cost_s = one_view * len(cams)
    st.eval_total_s += one_view
    st.eval_cost_wall = st.wall_s


def _evaluate(model, cams, imgs, cfg, st: LoopState, log, interrupted, final=False) -> None:
    """The held-out PSNR, logged. A periodic evaluation (not `final`) is abandoned after a view
    past which the rest, at the views' measured mean cost, would break the evaluations' cap
    (`within_eval_cap`): a young volume model's first views can take ten times its later ones
    (lego-200 sdf: 47 s for the evaluation at 60 s of training, 4 s from 500 s on), time the
    budget then lacks for training. Its cost so far counts, and the full evaluation's projected
    cost is kept as the reserve for the final one."""
    n = len(cams)

    def go_on(done: int, spent: float) -> bool:
        nonlocal projected
        projected = spent * n / done
        return final or within_eval_cap(cfg, st, projected)

    projected = 0.0
    t0 = time.perf_counter()
    psnr = heldout_psnr(model, cams, imgs, interrupted, go_on)
    spent = time.perf_counter() - t0
    st.eval_total_s += spent
    st.eval_cost_s = spent if psnr is not None else projected
    st.eval_cost_wall = st.last_eval_wall = st.wall_s
    if psnr is None:
        log(
            {
                "step": st.step,
                "wall_s": round(st.wall_s, 4),
                "event": "eval_deferred",
                "eval_s": round(spent, 3),
                "projected_s": round(projected, 3),
            }
        )
        return
    st.last_psnr_wall = st.wall_s
    if psnr > st.best_psnr + cfg.min_improvement_db:
        st.best_psnr, st.evals_since_best = psnr, 0
    else:
        st.best_psnr = max(st.best_psnr, psnr)
        st.evals_since_best += 1
    log(
        {
            "step": st.step,
            "wall_s": round(st.wall_s, 4),
            "test_psnr": round(psnr, 4),
            "eval_s": round(st.eval_cost_s, 3),
            "elapsed_s": round(st.elapsed_s + st.eval_cost_s, 3),
        }
    )


def _round(stats: dict) -> dict:
    return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in stats.items()}
