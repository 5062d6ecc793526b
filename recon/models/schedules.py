"""Learning-rate schedules: the one decay every method uses, and setting an optimizer's rate."""

from __future__ import annotations

import torch


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
