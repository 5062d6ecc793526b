"""A moving average of a model's parameters over the last steps of a run, which the run ends as.

A step fits one view (3dgs) or one batch of rays, so the last iterate of a run is the optimum
plus the pull of the last few views: on fox's 30-minute run the held-out PSNR of successive
iterates, 100 steps apart, wanders over 0.6 dB long after it stopped rising, and the run ended
0.4 dB under the average of its last steps (bench/results/2026-11-29-3dgs-average.md).
Averaging the iterates (Polyak & Juditsky 1992; Ruppert 1988) removes that noise without
lowering the rates that still make progress; an exponential moving average with a window of
`window` steps forgets the early, worse iterates of a long tail (as the weight averaging of
Izmailov et al. 2018, "Averaging Weights Leads to Wider Optima", Sec. 3, but exponential).

The average starts from the parameters of the first step it is asked for, as a uniform mean
while it holds fewer than `window` steps, an exponential one after (`average_weight`): no bias
towards the starting point, and no start-up phase to correct (Kingma & Ba 2015, Sec. 3, need
theirs because they start from zero).
"""

from __future__ import annotations

import torch
from torch import Tensor


def average_weight(count: int, window: float) -> float:
    """The weight of the `count`-th (1-based) value in the running average: 1 / count while
    count <= window (the mean of the values so far), 1 / window after (an exponential moving
    average whose time constant is `window` values)."""
    if count < 1 or window < 1:
        raise ValueError(f"count and window must be >= 1, got {count} and {window}")
    return max(1.0 / count, 1.0 / window)


class ParameterAverage:
    """The running average (`average_weight`) of a list of tensors, updated in place:
    `update(tensors, window)` after each step, `copy_to(tensors)` to end as the average."""

    def __init__(self, tensors: list[Tensor]):
        self.values = [t.detach().clone() for t in tensors]
        self.count = 1

    def matches(self, tensors: list[Tensor]) -> bool:
        """The tensors are the averaged ones' kind: as many, of the same shapes, dtypes and
        devices (a model that resized its parameters starts a new average)."""
        return len(tensors) == len(self.values) and all(
            t.shape == v.shape and t.dtype == v.dtype and t.device == v.device
            for t, v in zip(tensors, self.values)
        )

    @torch.no_grad()
    def update(self, tensors: list[Tensor], window: float) -> None:
        self.count += 1
        weight = average_weight(self.count, window)
        torch._foreach_lerp_(self.values, [t.detach() for t in tensors], weight)

    @torch.no_grad()
    def copy_to(self, tensors: list[Tensor]) -> None:
        if not self.matches(tensors):
            raise ValueError("the tensors are not those averaged")
        for t, v in zip(tensors, self.values):
            t.copy_(v)

    def state_dict(self) -> dict:
        return {"values": list(self.values), "count": self.count}

    @classmethod
    def from_state_dict(cls, state: dict, device: torch.device | None = None) -> ParameterAverage:
        average = cls([v.to(device) if device is not None else v for v in state["values"]])
        average.count = int(state["count"])
        return average
