"""Plane-sweep stereo (Collins 1996): a depth per reference pixel by photo-consistency.

For each hypothesis plane z = z_d (fronto-parallel to the reference camera), every reference
pixel u is lifted to X_ref = z_d K_ref^-1 [u, 1], mapped into a source camera
(src_from_ref X_ref) and the source image is sampled there; the windowed normalized
cross-correlation (NCC) between the reference and that warped source image scores the plane
at every pixel. The scores of the best `top_k` sources are averaged (occlusion-robust, as in
Kang, Szeliski & Chai 2001), the best plane wins, and a parabola through the scores at the
winner and its two neighbours refines it below the plane spacing. Planes are spaced uniformly
in inverse depth (equal steps in disparity).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from recon.cameras.rays import pixel_centers, project_points, unproject_pixels


def box_mean(x: Tensor, window: int) -> Tensor:
    """Mean over the window x window neighbourhood of each pixel of x (N, 1, H, W), averaging
    only pixels inside the image at the borders. window is odd. Summed-area differences
    (Crow 1984) along each axis in turn: the part of a window inside the image is a
    rectangle, so its mean is the mean of its rows' means; O(1) per pixel for any window."""
    return _running_mean(_running_mean(x, window // 2, -1), window // 2, -2)


def _running_mean(x: Tensor, r: int, dim: int) -> Tensor:
    """Mean of x over [i - r, i + r] along `dim`, clipped to the tensor's extent."""
    n = x.shape[dim]
    c = torch.cumsum(x, dim)
    head = list(x.shape)
    head[dim] = r + 1
    tail = [-1] * x.dim()
    tail[dim] = r
    padded = torch.cat([c.new_zeros(head), c, c.narrow(dim, n - 1, 1).expand(*tail)], dim)
    total = padded.narrow(dim, 2 * r + 1, n) - padded.narrow(dim, 0, n)
    i = torch.arange(n, device=x.device)
    count = (torch.clamp(i + r, max=n - 1) - torch.clamp(i - r, min=0) + 1).to(x.dtype)
    shape = [1] * x.dim()
    shape[dim] = n
    return total / count.view(shape)


def patch_stats(a: Tensor, window: int, eps: float = 1e-6) -> tuple[Tensor, Tensor]:
    """Windowed mean and variance (clamped at eps) of a (N, 1, H, W): `windowed_ncc`'s
    statistics of one image, computed once when it is compared with many."""
    mean = box_mean(a, window)
    return mean, (box_mean(a * a, window) - mean * mean).clamp_min(eps)


def windowed_ncc(a: Tensor, b: Tensor, window: int, eps: float = 1e-6) -> Tensor:
    """Normalized cross-correlation of a, b (N, 1, H, W) over window x window patches:

        NCC = cov(a, b) / sqrt(var(a) var(b)),  with cov = E[ab] - E[a]E[b] over the patch,

    in [-1, 1], invariant to a gain and an offset on either image (Hannah 1974). Variances are
    clamped at eps, so a flat patch scores ~0, not NaN. Returns (N, 1, H, W).
    Example: b = 2 a + 0.1 gives 1 wherever the patch of a is not flat; b = -a gives -1.
    """
    return ncc_against(patch_stats(a, window, eps), a, b, window, eps)


def ncc_against(stats_a: tuple[Tensor, Tensor], a: Tensor, b: Tensor, window: int, eps=1e-6):
    """`windowed_ncc(a, b)` with a's (mean, variance) from `patch_stats` given; stats and a
    broadcast against b (N, 1, H, W)."""
    mean_a, var_a = stats_a
    mean_b, var_b = patch_stats(b, window, eps)
    cov = box_mean(a * b, window) - mean_a * mean_b
    return (cov / torch.sqrt(var_a * var_b)).clamp(-1.0, 1.0)


def inverse_depth_planes(near: float, far: float, count: int) -> Tensor:
    """(D,) plane depths from near to far, uniform in 1/z (count >= 2, 0 < near < far)."""
    inv = torch.linspace(1.0 / near, 1.0 / far, count, dtype=torch.float64)
    return (1.0 / inv).float()


def warp_to_planes(
    source: Tensor, K_ref: Tensor, K_src: Tensor, src_from_ref: Tensor, planes: Tensor, size
) -> tuple[Tensor, Tensor]:
    """The source image (H_s, W_s) seen from the reference pixels on each plane.

    source: (H_s, W_s) grey; K_ref, K_src: (3, 3); src_from_ref: (4, 4) rigid; planes: (P,)
    depths in the reference frame; size: the reference image's (W, H). Returns the warped
    images (P, 1, H, W) (bilinear, 0 outside) and (P, H, W) bool: the point lands inside the
    source image, in front of it.
    """
    W, H = size
    uv = pixel_centers(W, H, device=source.device, dtype=source.dtype)
    rays = unproject_pixels(uv, uv.new_ones(H, W), K_ref)  # (H, W, 3) on z = 1
    # src_from_ref (z ray) = z (R ray) + t: rotate the rays once, not every plane's points
    rotated = rays @ src_from_ref[:3, :3].T
    in_src = torch.addcmul(src_from_ref[:3, 3], planes[:, None, None, None], rotated)
    uv_src, z_src = project_points(in_src, K_src)
    Hs, Ws = source.shape
    grid = torch.stack([uv_src[..., 0] / Ws * 2 - 1, uv_src[..., 1] / Hs * 2 - 1], dim=-1)
    valid = (grid.abs() <= 1).all(-1) & (z_src > 0)
    image = source[None, None].expand(len(planes), 1, Hs, Ws)
    warped = F.grid_sample(image, grid, align_corners=False, padding_mode="zeros")
    return warped, valid


def sweep_scores(
    reference: Tensor,
    sources: list[Tensor],
    K_ref: Tensor,
    K_srcs: list[Tensor],
    src_from_ref: list[Tensor],
    planes: Tensor,
    window: int,
    top_k: int,
    chunk: int = 16,
) -> Tensor:
    """(D, H, W) photo-consistency of every plane at every reference pixel: the mean of the
    top_k best sources' windowed NCC (a source that does not see the point scores -1).

    reference: (H, W) grey; sources: S images (H_s, W_s); K_*: (3, 3); src_from_ref: S (4, 4);
    planes: (D,). Planes are processed `chunk` at a time to bound memory (S chunk H W floats).
    """
    H, W = reference.shape
    top_k = min(top_k, len(sources))
    out = reference.new_empty(len(planes), H, W)
    ref = reference[None, None]
    stats = patch_stats(ref, window)
    for start in range(0, len(planes), chunk):
        z = planes[start : start + chunk]
        per_source = []
        for src, K_src, m in zip(sources, K_srcs, src_from_ref):
            warped, valid = warp_to_planes(src, K_ref, K_src, m, z, (W, H))
            score = ncc_against(stats, ref, warped, window)[:, 0]
            per_source.append(torch.where(valid, score, -1.0))
        best = torch.stack(per_source).topk(top_k, dim=0).values  # (top_k, chunk, H, W)
        out[start : start + len(z)] = best.mean(0)
    return out


def best_depth(scores: Tensor, planes: Tensor) -> tuple[Tensor, Tensor]:
    """Winner-take-all over the planes with a parabolic sub-plane refinement.

    scores: (D, H, W); planes: (D,) uniform in inverse depth. With s-, s0, s+ the scores at the
    winner d and its neighbours, the parabola's peak is at d + delta,
    delta = (s- - s+) / (2 (s- - 2 s0 + s+)), clamped to [-1/2, 1/2] (0 at the end planes or
    where the scores are not concave); the depth is interpolated in inverse depth there.
    Returns depth (H, W) and the winning score (H, W).
    Example: scores 0.2, 0.8, 0.6 about plane d -> delta = (0.2 - 0.6) / (2 (0.2 - 1.6 + 0.6))
    = 0.25.
    """
    D = scores.shape[0]
    score, d = scores.max(0)
    mid = d.clamp(1, D - 2)
    s_minus = scores.gather(0, (mid - 1)[None])[0]
    s_zero = scores.gather(0, mid[None])[0]
    s_plus = scores.gather(0, (mid + 1)[None])[0]
    curvature = s_minus - 2 * s_zero + s_plus
    interior = (d > 0) & (d < D - 1) & (curvature < -1e-9)
    delta = torch.where(interior, (s_minus - s_plus) / (2 * curvature.clamp(max=-1e-9)), 0.0)
    position = d.to(scores.dtype) + delta.clamp(-0.5, 0.5)
    inverse = 1.0 / planes.to(scores.dtype)
    lo = position.floor().long().clamp(0, D - 1)
    hi = (lo + 1).clamp(max=D - 1)
    frac = position - lo.to(scores.dtype)
    inv = inverse[lo] * (1 - frac) + inverse[hi] * frac
    return 1.0 / inv, score
