"""Gaussian count control by relocation (Kheradmand et al. 2024, "3D Gaussian Splatting as Markov
Chain Monte Carlo"): a stateless strategy, as `densify.DensifyStrategy` is for clone/split/prune
(their one interface: `strategy.Strategy`).

The Gaussians are read as samples of a distribution that the photometric loss shapes, and the
update becomes a Langevin step: after each optimizer step every mean gets Gaussian noise shaped
by its own covariance, gated so that only nearly transparent Gaussians move much,

    mu <- mu + lambda_noise * lr_mu * sigmoid(-k (o - t)) * Sigma eps,   eps ~ N(0, I),

with k = 100 and t = 0.005 (a Gaussian of opacity 0.1 gets 1e-4 of the noise). Every `interval`
steps the "dead" Gaussians (opacity <= min_opacity) are moved onto live ones drawn with
probability proportional to opacity, and the count grows by `growth` towards `cap` the same way.
A Gaussian that ends up as N copies at one place gets the opacity and scales that keep what
the copies composite to (`relocated`), so the move changes the image as little as it can. No
Gaussian is pruned and no opacity is reset. The loss adds L1 penalties on the opacities and the
scales (`regularizer`), so that Gaussians the views do not need fade and become relocatable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from recon.gaussians.optim import append_rows, zero_moment_rows
from recon.gaussians.projection import rotation_from_quats

NOISE_GATE_SHARPNESS = 100.0  # k of the noise gate sigmoid(-k (o - t))
NOISE_GATE_OPACITY = 0.005  # t: Gaussians below this opacity get at least half the noise


@dataclass(frozen=True)
class McmcStrategy:
    cap: int  # the count grows to this and no further
    growth: float = 0.05  # each refinement adds this fraction of the count (until the cap)
    min_opacity: float = 0.005  # Gaussians at or below this opacity are dead: relocated
    noise_lr: float = 5e5  # lambda_noise
    start: int = 500  # first refinement step
    stop: int = 25_000  # no relocation or growth from this step on (the noise goes on)
    interval: int = 100  # steps between refinements
    max_copies: int = 51  # copies beyond this at one Gaussian are counted as this many
    opacity_reg: float = 0.01  # L1 weight on the opacities in the loss (`regularizer`)
    scale_reg: float = 0.01  # L1 weight on the scales in the loss
    uses_abs_grad = False  # a class constant: not a field

    def regularizer(self, params: nn.ParameterDict) -> Tensor | None:
        return regularizer(params, self.opacity_reg, self.scale_reg)

    def post_backward(
        self, params, optimizer, state, splats, abs_grad, step, scene_extent, means_lr, generator
    ) -> dict[str, Tensor]:
        """`strategy.Strategy.post_backward`: `post_step` (no accumulators: `state` as given)."""
        post_step(self, params, optimizer, step, means_lr, scene_extent, generator)
        return state


def relocated(opacity: Tensor, scales: Tensor, copies: Tensor) -> tuple[Tensor, Tensor]:
    """opacity (N,) in (0, 1), scales (N, 3), copies (N,) >= 1 -> the opacity and scales each of
    `copies` identical Gaussians at one place must have to composite like the one they replace.

    Along a line through the centre the copies composite to 1 - (1 - o' g'(x))^n, which must
    equal o g(x) at the centre and integrate to the same: o' = 1 - (1 - o)^(1/n) and
    s' = s o / D with D = sum_{i=1..n} sum_{k=0..i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1)
    (Kheradmand et al. 2024, the relocation kernel). By the hockey-stick identity
    D = sum_{k=1..n} C(n, k) (-1)^(k-1) o'^k / sqrt(k), summed here in float64. n = 1 changes
    nothing; example: o = 0.75, n = 2 -> o' = 0.5, D = 2 * 0.5 - 0.25 / sqrt(2) = 0.82322,
    s' = 0.91105 s."""
    n = copies.to(torch.float64)
    o = opacity.to(torch.float64)
    o_new = 1 - (1 - o).clamp_min(1e-12) ** (1 / n)
    k = torch.arange(1, int(copies.max()) + 1, dtype=torch.float64, device=o.device)  # (K,)
    log_binom = (
        torch.lgamma(n[:, None] + 1) - torch.lgamma(k + 1) - torch.lgamma(n[:, None] - k + 1)
    )
    terms = torch.where(
        k <= n[:, None],
        torch.exp(log_binom) * (-1) ** (k - 1) * o_new[:, None] ** k / torch.sqrt(k),
        0.0,
    )
    ratio = o / terms.sum(-1)
    return o_new.to(opacity.dtype), scales * ratio.to(scales.dtype)[:, None]


def position_noise(
    quats: Tensor,
    log_scales: Tensor,
    opacity: Tensor,
    scale: float,
    generator: torch.Generator | None = None,
) -> Tensor:
    """quats (G, 4), log_scales (G, 3), opacity (G,) -> (G, 3): scale * gate(o) * Sigma eps with
    Sigma = R S^2 R^T, eps ~ N(0, I) and gate(o) = sigmoid(-k (o - t)) (the Langevin noise).
    A Gaussian's noise is drawn along its own axes, each stretched by its squared scale."""
    eps = torch.randn(
        log_scales.shape, generator=generator, device=log_scales.device, dtype=log_scales.dtype
    )
    gate = torch.sigmoid(NOISE_GATE_SHARPNESS * (NOISE_GATE_OPACITY - opacity))
    R = rotation_from_quats(quats)
    local = (R.transpose(-1, -2) @ eps[..., None])[..., 0] * torch.exp(2 * log_scales)
    return scale * gate[:, None] * (R @ local[..., None])[..., 0]


def regularizer(params: nn.ParameterDict, opacity_weight: float, scale_weight: float) -> Tensor:
    """opacity_weight * mean(o) + scale_weight * mean(s): L1 penalties on every Gaussian's
    opacity and scales (in scene units), which let unneeded Gaussians die and be relocated."""
    opacity = torch.sigmoid(params["opacity_logits"]).mean()
    return opacity_weight * opacity + scale_weight * torch.exp(params["log_scales"]).mean()


def _opacity(params: nn.ParameterDict) -> Tensor:
    return torch.sigmoid(params["opacity_logits"].detach()).reshape(-1)


def _share(strategy: McmcStrategy, params: nn.ParameterDict, optimizer, sources: Tensor) -> None:
    """Give every Gaussian in `sources` (indices, with repeats) the opacity and scales of one of
    its 1 + (times drawn) copies, and zero its Adam moments."""
    counts = torch.bincount(sources, minlength=params["means"].shape[0])[sources] + 1
    opacity, scales = relocated(
        _opacity(params)[sources],
        torch.exp(params["log_scales"].detach()[sources]),
        counts.clamp_max(strategy.max_copies),
    )
    eps = torch.finfo(opacity.dtype).eps
    opacity = opacity.clamp(strategy.min_opacity, 1 - eps)
    logits = params["opacity_logits"]
    logits.data[sources] = torch.logit(opacity).reshape(-1, *logits.shape[1:]).to(logits)
    params["log_scales"].data[sources] = torch.log(scales)
    zero_moment_rows(optimizer, sources)


def _draw(opacity: Tensor, count: int, generator: torch.Generator | None) -> Tensor:
    """`count` indices drawn with replacement, with probability proportional to opacity."""
    return torch.multinomial(opacity, count, replacement=True, generator=generator)


@torch.no_grad()
def relocate_dead(
    strategy: McmcStrategy,
    params: nn.ParameterDict,
    optimizer: torch.optim.Adam,
    generator: torch.Generator | None = None,
) -> int:
    """Move every dead Gaussian onto a live one drawn by opacity; both take `relocated`
    opacities and scales. Returns how many moved."""
    opacity = _opacity(params)
    dead = opacity <= strategy.min_opacity
    n_dead, alive = int(dead.sum()), (~dead).nonzero()[:, 0]
    if n_dead == 0 or len(alive) == 0:
        return 0
    sources = alive[_draw(opacity[alive], n_dead, generator)]
    _share(strategy, params, optimizer, sources)
    targets = dead.nonzero()[:, 0]
    for p in params.values():
        p.data[targets] = p.data[sources]
    zero_moment_rows(optimizer, targets)
    return n_dead


@torch.no_grad()
def grow(
    strategy: McmcStrategy,
    params: nn.ParameterDict,
    optimizer: torch.optim.Adam,
    generator: torch.Generator | None = None,
) -> int:
    """Add min(cap, floor((1 + growth) G)) - G Gaussians as copies of live ones drawn by
    opacity (their moments start at zero). Returns how many were added."""
    n = params["means"].shape[0]
    n_new = max(min(strategy.cap, math.floor((1 + strategy.growth) * n)) - n, 0)
    opacity = _opacity(params)
    if n_new == 0 or not bool((opacity > 0).any()):
        return 0
    sources = _draw(opacity, n_new, generator)
    _share(strategy, params, optimizer, sources)
    append_rows(params, optimizer, {name: p.detach()[sources] for name, p in params.items()})
    return n_new


@torch.no_grad()
def post_step(
    strategy: McmcStrategy,
    params: nn.ParameterDict,
    optimizer: torch.optim.Adam,
    step: int,
    means_lr: float,
    scene_extent: float,
    generator: torch.Generator | None = None,
) -> dict[str, int]:
    """After the optimizer step of 0-based `step`: relocate and grow every `interval` steps
    inside (start, stop), then add the position noise. The noise scale is
    noise_lr * means_lr / scene_extent (the means lr as a fraction of the extent, as the
    reference's normalised scenes have an extent of about 1). Returns the counts moved."""
    it = step + 1
    counts = {"relocated": 0, "added": 0}
    if strategy.start < it < strategy.stop and it % strategy.interval == 0:
        counts["relocated"] = relocate_dead(strategy, params, optimizer, generator)
        counts["added"] = grow(strategy, params, optimizer, generator)
    noise = position_noise(
        params["quats"].detach(),
        params["log_scales"].detach(),
        _opacity(params),
        strategy.noise_lr * means_lr / scene_extent,
        generator,
    )
    params["means"].data += noise
    return counts
