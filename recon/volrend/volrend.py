"""The volume-rendering quadrature shared by every volume method (Max 1995, "Optical
Models for Direct Volume Rendering"; Mildenhall et al. 2020, eq. 3):

    alpha_i = 1 - exp(-sigma_i delta_i),   T_i = exp(-sum_{j<i} sigma_j delta_j),
    w_i = T_i alpha_i,   C = sum_i w_i c_i + (1 - sum_i w_i) c_bg.

Samples are intervals [t_start, t_end) along a ray, in one of two layouts:
  padded (R, S): every ray has S samples (dense stratified / hierarchical sampling);
  packed (N,) + `ray_indices` (N,) int64: a variable number of samples per ray, as produced by
  occupancy-grid skipping. Samples of one ray must be contiguous and in front-to-back order
  (`ray_indices` non-decreasing).

The renderer never sees a model: it takes densities and colours (or a closure producing them).
Transmittance is the exponential of an exclusive cumulative sum of optical depth, never a
product of (1 - alpha + eps): the product loses all precision once alpha ~ 1 and its epsilon
biases every weight.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

# Per-sample optical depth beyond which the packed cumulative sum clamps: exp(-50) ~ 2e-22 of
# transmittance is below float32 resolution, and the clamp bounds the global running sum so
# float64 keeps every ray's own sum exact to ~1e-8 however many rays precede it.
_TAU_CAP = 50.0


def exclusive_cumsum(x: Tensor, ray_indices: Tensor | None = None) -> Tensor:
    """S_i = sum_{j<i, same ray} x_j.

    Padded: x (..., S) -> (..., S), along the last axis.
    Packed: x (N, ...), ray_indices (N,) non-decreasing -> (N, ...), along the first axis (each
    row of trailing values is its own sequence over the ray's samples); a global float64 cumulative sum
    minus each ray's value at its first sample (found by `searchsorted`), so no Python loop.
    The global sum must stay well inside float64 range/precision (see `_TAU_CAP`).
    Example: x = [1, 2, 3, 4], ray_indices = [0, 0, 1, 1] -> [0, 1, 0, 3].
    """
    if ray_indices is None:
        inclusive = torch.cumsum(x, dim=-1)
        return inclusive - x
    x64 = x.double()
    before = torch.cumsum(x64, dim=0) - x64  # global exclusive sum
    first = torch.searchsorted(ray_indices, ray_indices)  # index of each ray's first sample
    # index_select, not before[first]: its backward is index_add, deterministic on multi-threaded CPUs
    return (before - before.index_select(0, first)).to(x.dtype)


def render_transmittance(tau: Tensor, ray_indices: Tensor | None = None) -> Tensor:
    """T_i = exp(-sum_{j<i} tau_j) with tau = sigma delta the optical depth of each interval.

    tau: (..., S) padded or (N,) packed (see `exclusive_cumsum`). Returns T of the same shape.
    Each tau_j is capped at 50 inside the sum only: T after it is < 2e-22 either way.
    """
    return torch.exp(-exclusive_cumsum(tau.clamp(max=_TAU_CAP), ray_indices))


def alpha_compositing(
    alpha: Tensor,
    ray_indices: Tensor | None = None,
    t_min: float = 0.0,
) -> tuple[Tensor, Tensor]:
    """Front-to-back compositing of per-sample opacities (the same sum as `render_weights` with
    alpha given instead of sigma delta; Kerbl et al. 2023, eq. 3): w_i = T_i alpha_i with the
    exclusive transmittance T_i = prod_{j<i} (1 - alpha_j), taken in log space as
    exp(sum_{j<i} log(1 - alpha_j)) (`render_transmittance` with tau = -log(1 - alpha)).

    t_min > 0 stops a ray as the 3DGS rasterizer does: from the first sample whose T_i (1 - alpha_i)
    would fall below t_min on, alpha counts as 0 (that sample included).
    alpha: (..., S) padded, or (N, ...) packed with ray_indices (N,) (see `exclusive_cumsum`);
    alpha < 1. Returns (weights, the alphas composited), both shaped like `alpha`.
    Example: alpha = (0.5, 0.5, 0.5) -> w = (0.5, 0.25, 0.125); with t_min = 0.2 the third
    sample (T (1 - alpha) = 0.125 < 0.2) is dropped: w = (0.5, 0.25, 0).
    """
    tau = (-torch.log1p(-alpha)).clamp(max=_TAU_CAP)
    if t_min > 0:
        behind = exclusive_cumsum(tau, ray_indices) + tau  # -log T_i (1 - alpha_i)
        stop = ((behind > -math.log(t_min)) & (alpha > 0)).to(alpha.dtype)
        stopped = exclusive_cumsum(stop, ray_indices) + stop > 0
        alpha = torch.where(stopped, torch.zeros_like(alpha), alpha)
        tau = (-torch.log1p(-alpha)).clamp(max=_TAU_CAP)
    return render_transmittance(tau, ray_indices) * alpha, alpha


def render_weights(
    sigmas: Tensor, t_starts: Tensor, t_ends: Tensor, ray_indices: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """w_i = T_i alpha_i with alpha_i = 1 - exp(-sigma_i (t_end_i - t_start_i)).

    sigmas, t_starts, t_ends: (..., S) padded or (N,) packed. Returns (weights, transmittance,
    alphas), each shaped like `sigmas`. alpha uses expm1 so sigma delta = 1e-8 keeps its value.
    Worked example: sigma = (0.1, 2, 5, 1), delta = 0.5 -> w = (0.048771, 0.601292, 0.321213,
    0.011302).
    """
    tau = sigmas * (t_ends - t_starts)
    alphas = -torch.expm1(-tau)
    trans = render_transmittance(tau, ray_indices)
    return trans * alphas, trans, alphas


def accumulate_along_rays(
    weights: Tensor,
    values: Tensor | None = None,
    ray_indices: Tensor | None = None,
    n_rays: int | None = None,
) -> Tensor:
    """sum_i w_i v_i per ray.

    Padded: weights (R, S), values (R, S, D) or None -> (R, D) or (R, 1).
    Packed: weights (N,), values (N, D) or None, ray_indices (N,) -> (n_rays, D) or (n_rays, 1).
    """
    src = weights[..., None] if values is None else weights[..., None] * values
    if ray_indices is None:
        return src.sum(dim=-2)
    if n_rays is None:
        raise ValueError("packed samples need n_rays")
    out = torch.zeros((n_rays, src.shape[-1]), dtype=src.dtype, device=src.device)
    return out.index_add(0, ray_indices, src)


def surface_depth(expected: Tensor, acc: Tensor) -> Tensor:
    """The depth of the surface a pixel or ray sees: the expected depth sum_i w_i d_i divided by
    the opacity acc = sum_i w_i where acc > 0, and 0 where nothing was hit. Every renderer's
    depth output goes through it (one formula, one epsilon). Example: w = (0.25, 0.25) at
    d = (2, 4) -> expected 1.5, acc 0.5 -> 3."""
    return torch.where(acc > 0, expected / acc.clamp_min(1e-10), torch.zeros_like(expected))


@dataclass
class VolumeRender:
    """Per-ray results of `volume_render`.

    rgb: (R, 3) composited on the background; acc: (R,) opacity sum_i w_i;
    depth: (R,) expected distance sum_i w_i t_mid_i, NOT divided by acc (as NeRF's depth map,
    Mildenhall et al. 2020); use `depth / acc.clamp_min(eps)` for the depth of the surface hit;
    weights, transmittance: per sample, padded (R, S) or packed (N,).
    """

    rgb: Tensor
    acc: Tensor
    depth: Tensor
    weights: Tensor
    transmittance: Tensor


def volume_render(
    sigmas: Tensor,
    rgbs: Tensor,
    t_starts: Tensor,
    t_ends: Tensor,
    ray_indices: Tensor | None = None,
    n_rays: int | None = None,
    background: Tensor | None = None,
) -> VolumeRender:
    """C = sum_i T_i alpha_i c_i + (1 - sum_i w_i) c_bg, depth = sum_i w_i (t_start_i + t_end_i)/2.

    sigmas, t_starts, t_ends: (R, S) padded or (N,) packed; rgbs: (R, S, 3) or (N, 3);
    ray_indices: (N,) for packed samples, with n_rays = R; background: (3,) or (R, 3), or None
    for black (Max 1995; Mildenhall et al. 2020, eq. 3). Example: sigma (0.1, 2, 5, 1), grey
    levels (0.2, 0.8, 0.5, 0.9), intervals of 0.5 from 0 -> 0.661566, acc 0.982578.
    """
    weights, trans, _ = render_weights(sigmas, t_starts, t_ends, ray_indices)
    acc = accumulate_along_rays(weights, None, ray_indices, n_rays)[..., 0]
    rgb = accumulate_along_rays(weights, rgbs, ray_indices, n_rays)
    t_mid = (0.5 * (t_starts + t_ends))[..., None]
    depth = accumulate_along_rays(weights, t_mid, ray_indices, n_rays)[..., 0]
    if background is not None:
        rgb = rgb + (1.0 - acc[..., None]) * background
    return VolumeRender(rgb, acc, depth, weights, trans)


RgbSigmaFn = Callable[[Tensor, Tensor, Tensor | None], tuple[Tensor, Tensor]]


def render_with_fn(
    rgb_sigma_fn: RgbSigmaFn,
    t_starts: Tensor,
    t_ends: Tensor,
    ray_indices: Tensor | None = None,
    n_rays: int | None = None,
    background: Tensor | None = None,
) -> VolumeRender:
    """`volume_render` with the field behind a closure, nerfacc style.

    rgb_sigma_fn(t_starts, t_ends, ray_indices) -> (rgbs (..., 3), sigmas (...)): the caller
    knows its rays and field; the renderer only sees intervals.
    """
    rgbs, sigmas = rgb_sigma_fn(t_starts, t_ends, ray_indices)
    return volume_render(sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays, background)
