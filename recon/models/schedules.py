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


def fit_schedules(config: C, windows: dict[str, tuple[float, float]]) -> C:
    """The config with every step schedule named in `windows` moved into its window of the
    planned run (`config.schedule_steps`, 0 = not planned): a schedule that ends after
    `latest x plan` is shortened to it, one that ends before `earliest x plan` is stretched to
    it, one inside the window is kept. A 10-minute CPU run of ~2,000 steps decays its learning
    rate (and stops densifying) in time, where a reference's 30,000-step schedule would end it
    mid-way at a high learning rate; a 30-minute run keeps densifying for its first half instead
    of spending two thirds of its steps on a frozen set of Gaussians. Example: windows
    {"lr_decay_steps": (1.0, 1.0), "densify_stop": (0.5, 0.7)}, lr_decay_steps 5,000 and
    densify_stop 2,000 -> (1,600, 1,120) for a 1,600-step plan, (3,600, 2,000) for 3,600 steps
    and (6,400, 3,200) for 6,400 steps."""
    if config.schedule_steps <= 0:
        return config
    plan = config.schedule_steps
    fitted = {}
    for name, (earliest, latest) in windows.items():
        low, high = max(1, round(earliest * plan)), max(1, round(latest * plan))
        fitted[name] = min(max(getattr(config, name), low), high)
    return replace(config, **fitted)
