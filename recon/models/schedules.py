"""Learning-rate schedules: the one decay every method uses, and setting an optimizer's rate."""

from __future__ import annotations

from dataclasses import replace
from typing import TypeVar

import torch

C = TypeVar("C")


def exp_decay_lr(step: int, lr: float, lr_final: float, decay_steps: int, start: int = 0) -> float:
    """lr until `start`, then lr (lr_final / lr)^t with t = (step - start) / (decay_steps - start)
    (log-linear between the two, as the 3DGS and Instant-NGP references decay), held at
    lr_final from decay_steps on. Example: lr 1e-2, lr_final 1e-3 over 1,000 steps -> 3.16e-3
    at step 500."""
    t = min(max((step - start) / max(decay_steps - start, 1), 0.0), 1.0)
    return lr * (lr_final / lr) ** t


def set_lr(optimizer: torch.optim.Optimizer, lr: float, group: str | None = None) -> None:
    """Set the learning rate of every parameter group, or only of the group named `group`."""
    for g in optimizer.param_groups:
        if group is None or g.get("name") == group:
            g["lr"] = lr


def fit_schedules(config: C, fractions: dict[str, float]) -> C:
    """The config with every step schedule named in `fractions` that outlasts the planned run
    (`config.schedule_steps`, 0 = not planned) shortened to end at its fraction of it: a
    10-minute CPU run of ~2,000 steps decays its learning rate (and stops densifying) in time,
    where a reference's 30,000-step schedule would end it mid-way at a high learning rate. Runs
    at least as long as the schedules keep them unchanged. Example: schedule_steps 1,600,
    {"lr_decay_steps": 1.0, "densify_stop": 0.7}, lr_decay_steps 5,000 and densify_stop 2,000
    -> 1,600 and 1,120."""
    if config.schedule_steps <= 0:
        return config
    fitted = {
        name: min(getattr(config, name), max(1, round(fraction * config.schedule_steps)))
        for name, fraction in fractions.items()
    }
    return replace(config, **fitted)


def refit_schedules(
    planned: C, current: C, fractions: dict[str, float], schedule_steps: int, step: int
) -> C:
    """The `current` config re-fitted mid-run, before 0-based `step`, to a run now expected to
    last `schedule_steps` steps: each schedule named in `fractions` as `fit_schedules` would
    fit the `planned` config (the one fitted when the run began) into min(schedule_steps,
    planned length): an estimate that grows again (a slow stretch was a one-off) lengthens
    the schedules back, never beyond the plan. A schedule never ends in the past: one that
    would is ended at step + 1 (what was due at its end, such as the last densification's
    pruning, still happens once); one that has already ended stays as it was, and so does a
    step interval that has already fired (an opacity reset: shrinking it would fire it again
    at an arbitrary step). Example: fractions {"lr_decay_steps": 1.0, "densify_stop": 0.7},
    planned 3,359 and 2,351, re-fitted to 2,100 steps at step 1,000 -> 2,100 and 1,470; then
    to 2,500 at step 1,200 -> 2,500 and 1,750."""
    if planned.schedule_steps <= 0:
        return current
    length = min(schedule_steps, planned.schedule_steps)
    fitted = {}
    for name, fraction in fractions.items():
        now = getattr(current, name)
        if now <= step:  # ended (or an interval that has fired): stays
            continue
        target = min(getattr(planned, name), max(1, round(fraction * length)))
        fitted[name] = max(target, step + 1)
    return replace(current, schedule_steps=length, **fitted)


def schedule_state(config: C, fractions: dict[str, float]) -> dict[str, int]:
    """The re-plannable schedules of a config (`refit_schedules`) as a checkpoint keeps them:
    `replace(config, **state)` restores them exactly, clamps and ended schedules included."""
    return {name: getattr(config, name) for name in ("schedule_steps", *fractions)}
