"""Adam over per-attribute Gaussian tensors, and the row surgery densification needs: every
op that adds, removes or resets Gaussians rewrites the parameter AND its Adam moments, so the
optimizer state always has the parameters' shapes (gsplat's `_update_param_with_optimizer`).

`params` is an `nn.ParameterDict` name -> (G, ...) tensor; the optimizer has one group per
name with `group["name"]` set.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

MOMENTS = ("exp_avg", "exp_avg_sq")


def make_adam(params: nn.ParameterDict, lrs: dict[str, float]) -> torch.optim.Adam:
    """One Adam group per attribute, eps = 1e-15 as the reference; fused kernel (one pass over
    memory per tensor: ~4x faster than the per-op loop on a 2-core CPU at 50k Gaussians)."""
    groups = [{"params": [p], "lr": lrs[name], "name": name} for name, p in params.items()]
    return torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=True)


def update_rows(
    params: nn.ParameterDict,
    optimizer: torch.optim.Adam,
    param_fn: Callable[[str, Tensor], Tensor],
    moment_fn: Callable[[str, Tensor], Tensor],
    names: list[str] | None = None,
) -> None:
    """Replace params[name] by param_fn(name, old) and each Adam moment m by moment_fn(name, m),
    for every name in `names` (default all), keeping the Adam step count."""
    for group in optimizer.param_groups:
        name = group["name"]
        if names is not None and name not in names:
            continue
        old = group["params"][0]
        new = nn.Parameter(param_fn(name, old.detach()), requires_grad=old.requires_grad)
        state = optimizer.state.pop(old, {})
        for key in MOMENTS:
            if key in state:
                state[key] = moment_fn(name, state[key])
        if state:
            optimizer.state[new] = state
        group["params"][0] = new
        params[name] = new


def keep_rows(params: nn.ParameterDict, optimizer: torch.optim.Adam, keep: Tensor) -> None:
    """Prune: keep the rows where keep (G,) bool is True, in parameters and moments."""
    update_rows(params, optimizer, lambda _, x: x[keep], lambda _, m: m[keep])


def append_rows(
    params: nn.ParameterDict, optimizer: torch.optim.Adam, rows: dict[str, Tensor]
) -> None:
    """Clone/split: append new rows (N, ...) per attribute; their moments start at zero."""
    update_rows(
        params,
        optimizer,
        lambda name, x: torch.cat([x, rows[name].to(x)]),
        lambda name, m: torch.cat([m, torch.zeros_like(rows[name]).to(m)]),
    )


def reset_rows(
    params: nn.ParameterDict, optimizer: torch.optim.Adam, name: str, value: Tensor
) -> None:
    """Overwrite one attribute (e.g. the opacity reset) and zero its moments."""
    update_rows(
        params, optimizer, lambda _, x: value.to(x), lambda _, m: torch.zeros_like(m), names=[name]
    )


def zero_moment_rows(optimizer: torch.optim.Adam, rows: Tensor) -> None:
    """Zero the Adam moments of the given rows (indices or mask) of every attribute, in place:
    rows whose parameters were overwritten (relocated Gaussians) restart their moments."""
    for group in optimizer.param_groups:
        state = optimizer.state.get(group["params"][0], {})
        for key in MOMENTS:
            if key in state:
                state[key][rows] = 0
