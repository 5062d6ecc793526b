"""Adaptive density control (Kerbl et al. 2023, Sec. 5.2), as a stateless strategy dataclass plus a state dict of accumulators (gsplat style; the interface: `strategy.Strategy`).

Per step, for every Gaussian visible in the view, accumulate |dL/d mu'_ndc| (the 2D mean
gradient in NDC units, dL/d mu'_px * (W/2, H/2), as the reference) and the largest screen
radius. Every `interval` steps inside [start, stop), Gaussians whose mean gradient reaches
`grad_threshold` are cloned (small: max scale <= dense_fraction * extent) or split (large:
two children sampled from N(mu, Sigma), scales / 1.6); then Gaussians with opacity < 0.005 or,
after the first opacity reset, too large on screen or in the world are pruned. Every
`reset_interval` steps opacities are clamped to <= 0.01.

With `abs_grad` the accumulated quantity is the norm of the per-splat sums of the absolute
per-pixel gradients, sum_p |dL_p/dmu'| componentwise (Ye et al. 2024, "AbsGS", eq. 6): a
Gaussian that covers both sides of an edge or a texture gets gradients of opposite signs from
its pixels, which cancel in dL/dmu' and leave it large and blurry; their absolute values do not
cancel. The sum of absolute values is larger, hence the higher threshold (gsplat: 0.0008).

With `pixel_weights` the mean over views is weighted by the Gaussian's screen area in each
view (Zhang et al. 2024, "Pixel-GS": sum_k m_k |g_k| / sum_k m_k, m_k its pixels in view k;
here m_k = pi r_k^2 from the 3-sigma screen radius, clipped to the image). A Gaussian that is
large in the few views that see it from close by and small in the many that see it from afar
is otherwise judged by the far views' small gradients and left large and blurry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from recon.gaussians.optim import append_rows, keep_rows, reset_rows
from recon.gaussians.projection import rotation_from_quats
from recon.options import opt

RESET_OPACITY = 0.01  # opacity after a reset; Gaussians the views do not need fade below 0.005


@dataclass(frozen=True)
class DensifyStrategy:
    grad_threshold: float = opt(0.0002, "mean NDC positional-gradient norm that triggers densify")
    dense_fraction: float = opt(0.01, "clone if max scale <= this x scene extent, else split")
    split_shrink: float = opt(1.6, "split children get scales / this (0.8 x 2 children)")
    prune_opacity: float = opt(0.005, "prune Gaussians less opaque than this")
    prune_screen_fraction: float = opt(0.15, "prune if the screen radius passed this x max(W, H)")
    prune_world_fraction: float = opt(0.1, "prune if the max scale passed this x scene extent")
    start: int = opt(500, "first step that densifies")
    stop: int = opt(15000, "no densification or opacity reset from this step on")
    interval: int = opt(100, "densify every this many steps")
    reset_interval: int = opt(3000, "opacity reset every this many steps")
    max_gaussians: int = opt(3_000_000, "densification never grows the count beyond this")
    clone_opacity_correction: bool = opt(False, "clone and original get 1 - sqrt(1 - o) each")
    abs_grad: bool = opt(
        False, "accumulate sum_p |dL_p/dmu'| (AbsGS) instead of |dL/dmu'|: ~4x the threshold"
    )
    pixel_weights: bool = opt(
        False, "average the gradient over views weighted by screen area (Pixel-GS), not per view"
    )

    @property
    def uses_abs_grad(self) -> bool:
        return self.abs_grad

    def regularizer(self, params: nn.ParameterDict) -> Tensor | None:
        return None

    def post_backward(
        self, params, optimizer, state, splats, abs_grad, step, scene_extent, means_lr, generator
    ) -> dict[str, Tensor]:
        """`strategy.Strategy.post_backward`: the view's 2D gradients into the accumulators
        (before `stop`), then `post_step`'s schedule."""
        if step + 1 < self.stop:
            grad = splats.means2d.grad if abs_grad is None else abs_grad
            accumulate(state, grad, splats.radii, splats.width, splats.height, self.pixel_weights)
        return post_step(self, params, optimizer, state, step, scene_extent, generator)


def init_state(n: int, device=None) -> dict[str, Tensor]:
    """Accumulators for n Gaussians: NDC gradient-norm sum, visible-step count, max radius."""
    zeros = torch.zeros(n, device=device)
    return {"grad2d": zeros, "count": zeros.clone(), "radii": zeros.clone()}


@torch.no_grad()
def accumulate(
    state: dict[str, Tensor],
    grad_means2d: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    pixel_weights: bool = False,
) -> None:
    """In place: for visible Gaussians (radius > 0) add |dL/dmu'_px * (W/2, H/2)|, count one
    visible step and track max radius / max(W, H). grad_means2d (G, 2), radii (G,).
    With `pixel_weights` both sums are weighted by the screen area min(pi r^2, W H) (px)."""
    visible = radii > 0
    weight = visible.float()
    if pixel_weights:
        weight = torch.where(visible, (math.pi * radii.float() ** 2).clamp_max(width * height), 0.0)
    # scaled per axis by Python numbers: a tensor of them would be a host-to-device copy a step
    g = grad_means2d
    scaled = torch.stack((g[:, 0] * (width / 2.0), g[:, 1] * (height / 2.0)), dim=-1)
    state["grad2d"] += weight * scaled.norm(dim=-1)
    state["count"] += weight
    state["radii"] = torch.maximum(state["radii"], radii / max(width, height))


def _candidates(strategy: DensifyStrategy, state: dict[str, Tensor], n: int) -> Tensor:
    """(G,) bool: mean gradient >= threshold, capped to the top max_gaussians - n by gradient."""
    count = state["count"]
    mean_grad = torch.where(count > 0, state["grad2d"] / count.clamp_min(1e-12), 0.0)
    chosen = mean_grad >= strategy.grad_threshold
    budget = max(strategy.max_gaussians - n, 0)
    if int(chosen.sum()) > budget:
        top = torch.topk(torch.where(chosen, mean_grad, -1.0), budget).indices
        chosen = torch.zeros_like(chosen)
        chosen[top] = True
    return chosen


def _split_children(
    params: nn.ParameterDict, split: Tensor, shrink: float, generator: torch.Generator | None
) -> dict[str, Tensor]:
    """Two children per split Gaussian: mu + R (s * eps), eps ~ N(0, I); log-scales - log 1.6."""
    rows = {name: p.detach()[split].repeat(2, *([1] * (p.dim() - 1))) for name, p in params.items()}
    scales = torch.exp(rows["log_scales"])
    eps = torch.randn(scales.shape, generator=generator, device=scales.device, dtype=scales.dtype)
    R = rotation_from_quats(rows["quats"])
    rows["means"] = rows["means"] + (R @ (scales * eps)[..., None])[..., 0]
    rows["log_scales"] = rows["log_scales"] - torch.log(torch.tensor(shrink))
    return rows


@torch.no_grad()
def densify_and_prune(
    strategy: DensifyStrategy,
    params: nn.ParameterDict,
    optimizer: torch.optim.Adam,
    state: dict[str, Tensor],
    step: int,
    scene_extent: float,
    generator: torch.Generator | None = None,
) -> dict[str, int]:
    """Clone, split and prune in place (parameters and Adam moments). Returns the counts."""
    n = params["means"].shape[0]
    chosen = _candidates(strategy, state, n)
    small = torch.exp(params["log_scales"]).amax(-1) <= strategy.dense_fraction * scene_extent
    clone, split = chosen & small, chosen & ~small
    if strategy.clone_opacity_correction and bool(clone.any()):
        # Two identical splats at one depth composite to 1 - (1 - o')^2: with o' = 1 - sqrt(1 - o)
        # the clone leaves the render unchanged (Rota Bulo et al. 2024) instead of raising the
        # opacity there, which costs ~1 dB for tens of steps after every densification.
        o = torch.sigmoid(params["opacity_logits"].detach()[clone])
        halved = torch.logit(1 - torch.sqrt((1 - o).clamp_min(1e-12)), eps=1e-6)
        params["opacity_logits"].data[clone] = halved
    rows = _split_children(params, split, strategy.split_shrink, generator)
    rows = {k: torch.cat([params[k].detach()[clone], v]) for k, v in rows.items()}
    append_rows(params, optimizer, rows)
    n_new = rows["means"].shape[0]
    drop = torch.cat([split, torch.zeros(n_new, dtype=torch.bool, device=split.device)])
    drop |= torch.sigmoid(params["opacity_logits"]) < strategy.prune_opacity
    if step + 1 > strategy.reset_interval:
        too_big = (
            torch.exp(params["log_scales"]).amax(-1) > strategy.prune_world_fraction * scene_extent
        )
        on_screen = torch.cat([state["radii"], state["radii"].new_zeros(n_new)])
        drop |= too_big | (on_screen > strategy.prune_screen_fraction)
    keep_rows(params, optimizer, ~drop)
    return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int(drop.sum())}


def post_step(
    strategy: DensifyStrategy,
    params: nn.ParameterDict,
    optimizer: torch.optim.Adam,
    state: dict[str, Tensor],
    step: int,
    scene_extent: float,
    generator: torch.Generator | None = None,
) -> dict[str, Tensor]:
    """The schedule, run after the optimizer step of 0-based `step` (the reference counts from
    1). Returns the state to use next: fresh accumulators whenever the count changed."""
    it = step + 1
    if it >= strategy.stop:
        return state
    if it > strategy.start and it % strategy.interval == 0:
        densify_and_prune(strategy, params, optimizer, state, step, scene_extent, generator)
        state = init_state(params["means"].shape[0], params["means"].device)
    if it % strategy.reset_interval == 0:
        logit = torch.logit(torch.tensor(RESET_OPACITY)).item()
        reset_rows(
            params, optimizer, "opacity_logits", params["opacity_logits"].detach().clamp_max(logit)
        )
    return state
