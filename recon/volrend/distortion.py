"""mip-NeRF 360's distortion loss (Barron et al. 2022, eq. 15): a ray's weights should
concentrate on one short stretch of the ray, not spread as haze or floaters along it,

    L(s, w) = sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (s_{i+1} - s_i),

with m_i the midpoint of interval i in a normalized ray distance s (Barron et al. use s linear in
disparity; anything monotone in t that the caller finds natural). The double sum is O(S) with
prefix sums over each ray's intervals in front-to-back order (their Sec. 3 / appendix):

    sum_{i,j} w_i w_j |m_i - m_j| = 2 sum_i w_i (m_i W_i - V_i),
    W_i = sum_{j<i} w_j,  V_i = sum_{j<i} w_j m_j.
"""

from __future__ import annotations

from torch import Tensor

from recon.volrend.volrend import accumulate_along_rays, exclusive_cumsum


def distortion_loss(
    weights: Tensor, s_starts: Tensor, s_ends: Tensor, ray_indices: Tensor, n_rays: int
) -> Tensor:
    """L(s, w) (n_rays,) of packed intervals (N,) sorted front to back within each ray
    (`ray_indices` non-decreasing), differentiable in the weights. Rays without samples get 0.
    Example: one ray, intervals [0, 1], [1, 2], w = (0.5, 0.5): 2 * 0.25 * 1 + (0.25 + 0.25) / 3 = 2/3.
    """
    mid = 0.5 * (s_starts + s_ends)
    w_before = exclusive_cumsum(weights, ray_indices)
    wm_before = exclusive_cumsum(weights * mid, ray_indices)
    per_sample = (
        2.0 * weights * (mid * w_before - wm_before) + weights.square() * (s_ends - s_starts) / 3.0
    )
    return accumulate_along_rays(per_sample, None, ray_indices, n_rays)[:, 0]


def distortion_loss_reference(weights: Tensor, s_starts: Tensor, s_ends: Tensor) -> Tensor:
    """The same loss straight from its definition, O(S^2) per ray, for padded (R, S) intervals:
    the twin `distortion_loss` is tested against."""
    mid = 0.5 * (s_starts + s_ends)
    pairs = weights[:, :, None] * weights[:, None, :] * (mid[:, :, None] - mid[:, None, :]).abs()
    return pairs.sum((1, 2)) + (weights.square() * (s_ends - s_starts)).sum(-1) / 3.0
