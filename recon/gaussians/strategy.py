"""The one interface of the ways a 3DGS model's Gaussians are added, moved and removed during
training (the split of gsplat's `Strategy`): `densify.DensifyStrategy` (adaptive density control,
Kerbl et al. 2023) and `mcmc.McmcStrategy` (relocation, Kheradmand et al. 2024). Both are
stateless frozen dataclasses; what they accumulate between steps is a state dict the model
keeps and checkpoints."""

from __future__ import annotations

from typing import Protocol

import torch
from torch import Tensor, nn


class Strategy(Protocol):
    start: int  # the first step that changes the count
    stop: int  # no count changes from this step on
    uses_abs_grad: bool  # wants the rasterizer's per-splat sums of |dL_p/dmu'| (AbsGS)

    def regularizer(self, params: nn.ParameterDict) -> Tensor | None:
        """A term of the loss (before the backward pass), or None."""
        ...

    def post_backward(
        self,
        params: nn.ParameterDict,
        optimizer: torch.optim.Adam,
        state: dict[str, Tensor],
        splats,  # ProjectedSplats of the step's view, their means2d's gradient filled
        abs_grad: Tensor | None,
        step: int,
        scene_extent: float,
        means_lr: float,
        generator: torch.Generator | None,
    ) -> dict[str, Tensor]:
        """After the optimizer step of 0-based `step`: accumulate, and add / move / remove
        Gaussians (params and the optimizer's moments in place). Returns the state to keep."""
        ...
