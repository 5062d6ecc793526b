"""Where samples go along a ray (Mildenhall et al. 2020, Sec. 5.2): ray/box
intersection, stratified intervals in [near, far], and inverse-CDF resampling of a coarse
weight distribution. All functions return padded (R, S) interval tensors for `volrend`.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor


def uniform(shape: tuple[int, ...], like: Tensor, generator: torch.Generator | None) -> Tensor:
    """U[0, 1) of `like`'s dtype and device, drawn on the generator's own device (a CPU
    generator can then drive CUDA tensors reproducibly)."""
    dev = generator.device if generator is not None else like.device
    return torch.rand(shape, generator=generator, device=dev, dtype=like.dtype).to(like.device)


def ray_aabb_intersect(
    origins: Tensor, directions: Tensor, aabb: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Slab method: t_near = max_k min(t0_k, t1_k), t_far = min_k max(t0_k, t1_k),
    t0/1_k = (aabb[0/1, k] - o_k) / d_k.

    origins, directions: (R, 3); aabb: (2, 3) [min, max]. Returns t_near (R,) clamped at 0 (a
    ray starting inside the box starts at 0), t_far (R,), and hit (R,) bool (t_far > t_near).
    Axis-parallel rays (d_k = 0) get a tiny signed d_k, so the slab is either all of t or none.
    Missed rays keep t_near = t_far = 0 so no sample is ever placed on them.
    """
    tiny = torch.finfo(directions.dtype).tiny ** 0.5
    d = torch.where(directions.abs() < tiny, torch.full_like(directions, tiny), directions)
    inv = 1.0 / d
    t0 = (aabb[0] - origins) * inv
    t1 = (aabb[1] - origins) * inv
    t_near = torch.minimum(t0, t1).amax(dim=-1).clamp_min(0.0)
    t_far = torch.maximum(t0, t1).amin(dim=-1)
    hit = t_far > t_near
    zero = torch.zeros_like(t_near)
    return torch.where(hit, t_near, zero), torch.where(hit, t_far, zero), hit


def stratified_intervals(
    near: Tensor,
    far: Tensor,
    n_samples: int,
    jitter: bool,
    generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor]:
    """S intervals tiling [near, far]; with jitter, the interior edges e_k (k = 1..S-1) are drawn
    uniformly in [c_{k-1}, c_k], c the centres of the S equal bins, so every location in
    [near, far] is an interval midpoint with non-zero probability (unbiased quadrature).

    near, far: (R,). Returns t_starts, t_ends (R, S), with t_starts[:, 0] = near and
    t_ends[:, -1] = far. Without jitter the intervals are the S equal bins.
    """
    R, device, dtype = near.shape[0], near.device, near.dtype
    s = torch.linspace(0.0, 1.0, n_samples + 1, device=device, dtype=dtype).expand(R, -1)
    if jitter and n_samples > 1:
        centres = 0.5 * (s[:, 1:] + s[:, :-1])  # (R, S)
        u = uniform((R, n_samples - 1), near, generator)
        interior = centres[:, :-1] + (centres[:, 1:] - centres[:, :-1]) * u
        s = torch.cat([s[:, :1], interior, s[:, -1:]], dim=-1)
    edges = near[:, None] + (far - near)[:, None] * s
    return edges[:, :-1], edges[:, 1:]


def spaced_intervals(
    near: Tensor,
    far: Tensor,
    n_samples: int,
    jitter: bool,
    spacing: Callable[[Tensor], Tensor],
    spacing_inv: Callable[[Tensor], Tensor],
    generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor]:
    """Stratified in a warped coordinate s = g(t): intervals stratified in [g(near), g(far)] and
    mapped back through g^-1 (e.g. g(t) = 1/t, linear in disparity, for unbounded scenes)."""
    s0, s1 = stratified_intervals(spacing(near), spacing(far), n_samples, jitter, generator)
    return spacing_inv(s0), spacing_inv(s1)


def sample_pdf(
    edges: Tensor,
    weights: Tensor,
    n_samples: int,
    jitter: bool,
    generator: torch.Generator | None = None,
    eps: float = 1e-5,
) -> Tensor:
    """Inverse-transform sampling t = CDF^-1(u) of the piecewise-constant pdf p_i ~ w_i on the
    intervals [edges_i, edges_{i+1}) (the CDF is piecewise linear).

    edges: (R, S+1) sorted; weights: (R, S) >= 0. Returns t (R, n_samples) sorted. u is the
    midpoint grid (i + 0.5)/n without jitter, one uniform draw per stratum with jitter (stratified
    importance sampling). `eps` added to every weight keeps empty rays sampling uniformly.
    """
    R, S = weights.shape
    w = weights.detach() + eps
    pdf = w / w.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, dim=-1)], dim=-1)
    cdf[:, -1] = 1.0  # exact top so u < 1 always lands in a bin
    offsets = torch.arange(n_samples, device=w.device, dtype=w.dtype).expand(R, -1)
    if jitter:
        u = (offsets + uniform((R, n_samples), w, generator)) / n_samples
    else:
        u = (offsets + 0.5) / n_samples
    idx = torch.searchsorted(cdf, u.contiguous(), right=True).clamp(1, S)  # bin = idx - 1
    cdf_lo, cdf_hi = cdf.gather(1, idx - 1), cdf.gather(1, idx)
    e_lo, e_hi = edges.detach().gather(1, idx - 1), edges.detach().gather(1, idx)
    frac = ((u - cdf_lo) / (cdf_hi - cdf_lo).clamp_min(1e-12)).clamp(0.0, 1.0)
    return e_lo + frac * (e_hi - e_lo)


def intervals_from_points(t: Tensor, near: Tensor, far: Tensor) -> tuple[Tensor, Tensor]:
    """Intervals around sorted sample points: edges at the midpoints between neighbours, the first
    starting at `near` and the last ending at `far`. t: (R, S); near, far: (R,) -> (R, S) x2."""
    mids = 0.5 * (t[:, 1:] + t[:, :-1])
    starts = torch.cat([near[:, None].to(t.dtype), mids], dim=-1)
    ends = torch.cat([mids, far[:, None].to(t.dtype)], dim=-1)
    return starts, ends


def merge_points(t_a: Tensor, t_b: Tensor) -> Tensor:
    """Sorted union of two sets of sample points per ray: (R, Sa), (R, Sb) -> (R, Sa + Sb)."""
    return torch.sort(torch.cat([t_a, t_b], dim=-1), dim=-1).values
