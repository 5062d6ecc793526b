"""Fast CPU tile rasterizer (numba), forward and backward, as a `torch.autograd.Function`.

Per pixel p and its tile's depth-sorted list (Kerbl et al. 2023, Sec. 6):
    alpha_i = min(0.99, o_i exp(-0.5 d^T conic_i d)), d = mu_i - p, skipped if < 1/255,
    T_i = prod_{j<i} (1 - alpha_j), F(p) = sum_i T_i alpha_i f_i,
stopping before the splat that would take T below 1e-4. The forward saves the final T and the
index of the last contributor per pixel; the backward walks each list back to front recovering
T_i = T_{i+1} / (1 - alpha_i) and S_i = sum_{j>i} T_j alpha_j f_j:
    dF/df_i = T_i alpha_i,   dF/dalpha_i = T_i f_i - S_i / (1 - alpha_i),
    dT_final/dalpha_i = -T_final / (1 - alpha_i).
Tiles run in parallel (`prange` over interleaved tile chunks); within a tile each splat visits
only the pixels inside its alpha >= 1/255 ellipse d^T conic d <= 2 ln(255 o), row by row and
slightly widened (an exact bound: it changes speed, not results), with exp evaluated by an
exact multiplicative recurrence along each row. Backward gradients go to one buffer per thread
chunk, reduced once (deterministic for a given thread count). `rasterize_reference.py` is the slow
twin with the same semantics, `rasterize_torch.py` the vectorised torch version used on other
devices; tests compare all three on outputs and gradients.
"""

from __future__ import annotations

import math
import os

import numba
import numpy as np
import torch
from numba import prange
from torch import Tensor
from torch.profiler import record_function

from recon.gaussians.alpha import ALPHA_MAX, ALPHA_MIN, SLACK, T_MIN
from recon.gaussians.tiles import bin_gaussians, tile_bounds, tile_size

if "NUMBA_THREADING_LAYER" not in os.environ:
    # numba's OpenMP layer loads the system libgomp, torch ships its own: two OpenMP runtimes
    # whose idle threads spin against each other on a 2-core box (interleaved torch/numba work
    # measured several times slower, under load). The workqueue layer's threads sleep instead.
    # Takes effect only if no numba parallel region has run yet in this process.
    numba.config.THREADING_LAYER = "workqueue"

RECUR_MAX_A = 4.0  # conic x-curvatures up to this use the exp recurrence (no overflow risk)
FORWARD_CHUNKS = 64  # parallel work items of the forward, each a strided set of tiles
GRAD_COLUMNS = 8  # d mean2d (2), d conic (3), d opacity (1), |d mean2d| (2), then d features (D)


@numba.njit(cache=True)
def _pixel_range(lo, hi, start, stop):
    """Integers p in [start, stop) whose pixel centre p + 0.5 lies in [lo, hi]."""
    a = max(float(start), min(float(stop), math.ceil(lo - 0.5)))
    b = max(float(start), min(float(stop), math.floor(hi - 0.5) + 1.0))
    return int(a), int(b)


@numba.njit(cache=True)
def _ellipse(A, B, C, o, alpha_min):
    """The region where alpha = o exp(power) can reach alpha_min: power >= floor with
    floor = log(alpha_min / o) widened by SLACK (so this geometric culling never drops a pixel
    the exact test keeps), power = -0.5 (A dx^2 + 2 B dx dy + C dy^2).
    Returns (floor, positive definite?, det = AC - B^2, 1 / A, -2 A floor)."""
    floor = math.log(alpha_min / o) * (1.0 + SLACK) - SLACK
    det = float(A) * C - float(B) * B
    if not (det > 0 and A > 0):
        return floor, False, det, 0.0, 0.0
    return floor, True, det, 1.0 / A, -2.0 * A * floor


@numba.njit(cache=True)
def _row_range(my, ellipse, y0, y1):
    """Rows of [y0, y1) inside the ellipse: |dy| <= sqrt(-2 floor A / det) (= sqrt(-2 floor
    Sigma'_yy)); every row when the conic is not positive definite."""
    floor, pd, det, inv_a, _ = ellipse
    if not pd:
        return y0, y1
    ey = math.sqrt(-2.0 * floor / (det * inv_a))
    return _pixel_range(my - ey, my + ey, y0, y1)


@numba.njit(cache=True)
def _col_range(mx, dy, B, ellipse, x0, x1):
    """Columns of [x0, x1) inside the ellipse on the row at offset dy = my - row centre:
    A dx^2 + 2 B dy dx + C dy^2 + 2 floor <= 0 with dx = mx - column centre, i.e.
    |dx + B dy / A| <= sqrt(-det dy^2 - 2 A floor) / A."""
    _, pd, det, inv_a, c0 = ellipse
    if not pd:
        return x0, x1
    disc = c0 - det * dy * dy
    if disc < 0:
        return x0, x0
    half, centre = math.sqrt(disc) * inv_a, mx + B * dy * inv_a
    return _pixel_range(centre - half, centre + half, x0, x1)


@numba.njit(cache=True)
def _row_decay(ellipse, A):
    """exp(-A) for the row recurrence, or 0 to use one exp per pixel: non positive-definite
    conics and A > RECUR_MAX_A (needle-thin splats, where exp(A dx) could overflow)."""
    return math.exp(-float(A)) if ellipse[1] and A <= RECUR_MAX_A else 0.0


@numba.njit(cache=True)
def _gauss_row(mx, dy, A, B, C, centers, px0, px1, decay, out):
    """out[j] = exp(power) at columns px0 + j of the row at offset dy, 0 where power > 0.

    With decay = exp(-A) > 0 (from `_row_decay`) it uses the exact recurrence of a quadratic
    exponent instead of one exp per pixel: stepping dx -> dx - 1 multiplies G by
    r = exp(A dx - A/2 + B dy), and r by exp(-A). In float64, stored in out's dtype (the
    features'); the backward calls this same function, so both passes see bit-identical values."""
    dx = float(mx - centers[px0])
    dyf = float(dy)
    if decay > 0:
        gauss = math.exp(-0.5 * (A * dx * dx + C * dyf * dyf) - B * dx * dyf)
        ratio = math.exp(A * dx - 0.5 * A + B * dyf)
        for j in range(px1 - px0):
            out[j] = gauss
            gauss *= ratio
            ratio *= decay
    else:
        for j in range(px1 - px0):
            d = float(mx - centers[px0 + j])
            power = -0.5 * (A * d * d + C * dyf * dyf) - B * d * dyf
            out[j] = math.exp(power) if power <= 0 else 0.0


@numba.njit(cache=True)
def _rgb(features, g):
    """Features 0-2 of splat g (repeats of feature 0 when D < 3): the D = 3 fast paths of the
    kernels keep them, and their gradient sums, in registers instead of per-pixel array loops
    (fox-real 269 x 478, 103 k splats: forward ~15 %, backward ~10 % faster)."""
    D = features.shape[1]
    f0 = features[g, 0]
    return f0, features[g, 1] if D > 1 else f0, features[g, 2] if D > 2 else f0


@numba.njit(cache=True)
def _tile_box(t, width, height, tile):
    """Pixel box [x0, x1) x [y0, y1) of tile t (row-major tiles; edge tiles are clipped)."""
    tiles_x = (width + tile - 1) // tile
    x0, y0 = (t % tiles_x) * tile, (t // tiles_x) * tile
    return x0, y0, min(x0 + tile, width), min(y0 + tile, height)


@numba.njit(cache=True)
def _forward_tile(
    t,
    means2d,
    conics,
    opacities,
    features,
    tile_start,
    gauss_ids,
    width,
    height,
    tile,
    consts,
    centers,
    out_feat,
    out_T,
    out_last,
):
    alpha_max, alpha_min, t_min, one = consts[0], consts[1], consts[2], consts[4]
    D = features.shape[1]
    x0, y0, x1, y1 = _tile_box(t, width, height, tile)
    tw, n_pix = x1 - x0, (x1 - x0) * (y1 - y0)
    T = np.ones(n_pix, features.dtype)
    acc = np.zeros((n_pix, D), features.dtype)
    last = np.full(n_pix, -1, np.int32)
    done = np.zeros(n_pix, np.bool_)
    row = np.empty(tile, features.dtype)
    n_done = 0
    start = tile_start[t]
    for k in range(start, tile_start[t + 1]):
        g = gauss_ids[k]
        mx, my, o = means2d[g, 0], means2d[g, 1], opacities[g]
        A, B, C = conics[g, 0], conics[g, 1], conics[g, 2]
        if not o >= alpha_min:  # alpha <= o: never visible
            continue
        f0, f1, f2 = _rgb(features, g)
        ellipse = _ellipse(A, B, C, o, alpha_min)
        decay = _row_decay(ellipse, A)
        py0, py1 = _row_range(my, ellipse, y0, y1)
        for py in range(py0, py1):
            dy = my - centers[py]
            px0, px1 = _col_range(mx, dy, B, ellipse, x0, x1)
            if px1 <= px0:
                continue
            _gauss_row(mx, dy, A, B, C, centers, px0, px1, decay, row)
            for px in range(px0, px1):
                p = (py - y0) * tw + (px - x0)
                if done[p]:
                    continue
                alpha = min(alpha_max, o * row[px - px0])
                if alpha < alpha_min:
                    continue
                test_T = T[p] * (one - alpha)
                if test_T < t_min:
                    done[p] = True
                    n_done += 1
                    continue
                w = alpha * T[p]
                if D == 3:  # colour, the training case: the splat's features in registers
                    acc[p, 0] += f0 * w
                    acc[p, 1] += f1 * w
                    acc[p, 2] += f2 * w
                else:
                    for c in range(D):
                        acc[p, c] += features[g, c] * w
                T[p] = test_T
                last[p] = k - start
        if n_done == n_pix:
            break
    for p in range(n_pix):
        py, px = y0 + p // tw, x0 + p % tw
        out_T[py, px] = T[p]
        out_last[py, px] = last[p]
        for c in range(D):
            out_feat[py, px, c] = acc[p, c]


@numba.njit(parallel=True, fastmath=False, cache=True)
def _forward_kernel(
    means2d,
    conics,
    opacities,
    features,
    tile_start,
    gauss_ids,
    width,
    height,
    tile,
    consts,
    centers,
):
    # every pixel belongs to one tile, whose epilogue writes it: no serial fill first
    out_feat = np.empty((height, width, features.shape[1]), features.dtype)
    out_T = np.empty((height, width), features.dtype)
    out_last = np.empty((height, width), np.int32)
    n_tiles = tile_start.shape[0] - 1
    # Interleaved chunks: prange hands out contiguous blocks, and a block of image rows can
    # hold most of the work; tiles t, t + 64, ... cost about the same as any other such set.
    for chunk in prange(FORWARD_CHUNKS):
        for t in range(chunk, n_tiles, FORWARD_CHUNKS):
            _forward_tile(
                t,
                means2d,
                conics,
                opacities,
                features,
                tile_start,
                gauss_ids,
                width,
                height,
                tile,
                consts,
                centers,
                out_feat,
                out_T,
                out_last,
            )
    return out_feat, out_T, out_last


@numba.njit(cache=True)
def _backward_splat(
    g,
    i,
    box,
    means2d,
    conics,
    opacities,
    features,
    consts,
    centers,
    T,
    last,
    g_feat,
    g_T_final,
    S,
    g_f,
    row,
):
    """Gradients of splat g (position i in its tile's list) summed over the tile's pixels that
    it reached, walking back to front (updates T to T_i and S to S_i as it goes).
    Returns dL/d(mx, my, A, B, C, o) and sum over pixels of |dL_p/dmx|, |dL_p/dmy| (the
    per-pixel mean gradients' absolute values, Ye et al. 2024, eq. 6); dL/df goes to g_f."""
    alpha_max, alpha_min, half, one = consts[0], consts[1], consts[3], consts[4]
    x0, y0, x1, y1 = box
    tw = x1 - x0
    mx, my, o = means2d[g, 0], means2d[g, 1], opacities[g]
    A, B, C = conics[g, 0], conics[g, 1], conics[g, 2]
    ellipse = _ellipse(A, B, C, o, alpha_min)
    decay = _row_decay(ellipse, A)
    py0, py1 = _row_range(my, ellipse, y0, y1)
    g_mx = g_my = g_A = g_B = g_C = g_o = abs_mx = abs_my = 0.0
    g_f[:] = 0.0
    rgb = features.shape[1] == 3
    f0, f1, f2 = _rgb(features, g)
    g_f0 = g_f1 = g_f2 = 0.0
    for py in range(py0, py1):
        dy = my - centers[py]
        px0, px1 = _col_range(mx, dy, B, ellipse, x0, x1)
        if px1 <= px0:
            continue
        _gauss_row(mx, dy, A, B, C, centers, px0, px1, decay, row)
        for px in range(px0, px1):
            p = (py - y0) * tw + (px - x0)
            if last[p] < i:
                continue
            dx = mx - centers[px]
            gauss = row[px - px0]
            o_gauss = o * gauss
            alpha = min(alpha_max, o_gauss)
            if alpha < alpha_min:
                continue
            inv_one_minus = one / (one - alpha)  # one division instead of D + 2
            T[p] = T[p] * inv_one_minus  # T_i, transmittance in front of splat i
            w = alpha * T[p]
            g_alpha = -g_T_final[p] * inv_one_minus
            if rgb:
                T_i, d0, d1, d2 = T[p], g_feat[p, 0], g_feat[p, 1], g_feat[p, 2]
                g_f0 += d0 * w
                g_f1 += d1 * w
                g_f2 += d2 * w
                g_alpha += d0 * (T_i * f0 - S[p, 0] * inv_one_minus)
                g_alpha += d1 * (T_i * f1 - S[p, 1] * inv_one_minus)
                g_alpha += d2 * (T_i * f2 - S[p, 2] * inv_one_minus)
                S[p, 0] += w * f0
                S[p, 1] += w * f1
                S[p, 2] += w * f2
            else:
                for c in range(features.shape[1]):
                    g_f[c] += g_feat[p, c] * w
                    g_alpha += g_feat[p, c] * (T[p] * features[g, c] - S[p, c] * inv_one_minus)
                    S[p, c] += w * features[g, c]
            if o_gauss <= alpha_max:  # the 0.99 clamp passes no gradient
                g_o += g_alpha * gauss
                g_pow = g_alpha * o_gauss
                p_mx = g_pow * (A * dx + B * dy)
                p_my = g_pow * (B * dx + C * dy)
                g_mx -= p_mx
                g_my -= p_my
                abs_mx += abs(p_mx)
                abs_my += abs(p_my)
                g_A -= g_pow * half * dx * dx
                g_B -= g_pow * dx * dy
                g_C -= g_pow * half * dy * dy
    if rgb:
        g_f[0], g_f[1], g_f[2] = g_f0, g_f1, g_f2
    return g_mx, g_my, g_A, g_B, g_C, g_o, abs_mx, abs_my


@numba.njit(cache=True)
def _backward_tile(
    t,
    means2d,
    conics,
    opacities,
    features,
    tile_start,
    gauss_ids,
    width,
    height,
    tile,
    consts,
    centers,
    fwd_T,
    fwd_last,
    grad_feat,
    grad_T,
    grads,
):
    box = _tile_box(t, width, height, tile)
    x0, y0, x1, y1 = box
    tw, n_pix, D = x1 - x0, (x1 - x0) * (y1 - y0), features.shape[1]
    T = np.empty(n_pix, features.dtype)
    last = np.empty(n_pix, np.int32)
    g_feat = np.empty((n_pix, D), features.dtype)
    g_T_final = np.empty(n_pix, features.dtype)  # dL/dT_final * T_final
    S = np.zeros((n_pix, D), features.dtype)
    g_f = np.empty(D, features.dtype)
    row = np.empty(tile, features.dtype)
    max_last = -1
    for p in range(n_pix):
        py, px = y0 + p // tw, x0 + p % tw
        T[p], last[p] = fwd_T[py, px], fwd_last[py, px]
        g_T_final[p] = grad_T[py, px] * fwd_T[py, px]
        for c in range(D):
            g_feat[p, c] = grad_feat[py, px, c]
        max_last = max(max_last, last[p])
    start = tile_start[t]
    for k in range(start + max_last, start - 1, -1):
        g = gauss_ids[k]
        if not opacities[g] >= consts[1]:  # alpha <= o < 1/255: never reached a pixel
            continue
        g_splat = _backward_splat(
            g,
            k - start,
            box,
            means2d,
            conics,
            opacities,
            features,
            consts,
            centers,
            T,
            last,
            g_feat,
            g_T_final,
            S,
            g_f,
            row,
        )
        for j in range(GRAD_COLUMNS):
            grads[g, j] += g_splat[j]
        for c in range(D):
            grads[g, GRAD_COLUMNS + c] += g_f[c]


@numba.njit(parallel=True, fastmath=False, cache=True)
def _backward_kernel(
    means2d,
    conics,
    opacities,
    features,
    tile_start,
    gauss_ids,
    width,
    height,
    tile,
    consts,
    centers,
    fwd_T,
    fwd_last,
    grad_feat,
    grad_T,
    n_chunks,
):
    """Chunk c owns tiles c, c + n_chunks, ... and its own gradient buffer (no atomics);
    interleaving balances the load because neighbouring tiles cost about the same."""
    n_tiles = tile_start.shape[0] - 1
    G, D = features.shape
    grads = np.zeros((n_chunks, G, GRAD_COLUMNS + D), features.dtype)
    for chunk in prange(n_chunks):
        for t in range(chunk, n_tiles, n_chunks):
            _backward_tile(
                t,
                means2d,
                conics,
                opacities,
                features,
                tile_start,
                gauss_ids,
                width,
                height,
                tile,
                consts,
                centers,
                fwd_T,
                fwd_last,
                grad_feat,
                grad_T,
                grads[chunk],
            )
    return grads


def _numpy(x: Tensor, dtype: torch.dtype) -> np.ndarray:
    return x.detach().to(dtype).contiguous().numpy()


class _RasterizeFeatures(torch.autograd.Function):
    """(means2d, conics, opacities, features) -> (image (H, W, D), final transmittance (H, W)),
    computed in the dtype of `features`."""

    @staticmethod
    def forward(
        ctx,
        means2d,
        conics,
        opacities,
        features,
        tile_start,
        gauss_ids,
        width,
        height,
        tile,
        abs_grad,
    ):
        dt = features.dtype
        np_dt = _numpy(features, dt).dtype
        # Constants and pixel centres in the working dtype: float32 math stays float32 (expf
        # is ~2x cheaper than exp) instead of being promoted by float64 literals.
        consts = np.array([ALPHA_MAX, ALPHA_MIN, T_MIN, 0.5, 1.0], dtype=np_dt)
        centers = np.arange(max(width, height), dtype=np_dt) + np_dt.type(0.5)
        args = (
            _numpy(means2d, dt),
            _numpy(conics, dt),
            _numpy(opacities, dt),
            _numpy(features, dt),
            tile_start.numpy(),
            gauss_ids.numpy(),
            width,
            height,
            tile,
            consts,
            centers,
        )
        with record_function("3dgs.raster_forward"):
            image, T, last = _forward_kernel(*args)
        ctx.args, ctx.fwd, ctx.abs_grad = args, (T, last), abs_grad
        ctx.in_dtypes = (means2d.dtype, conics.dtype, opacities.dtype)
        return torch.from_numpy(image), torch.from_numpy(T)

    @staticmethod
    def backward(ctx, grad_image, grad_T):
        dt = torch.from_numpy(ctx.fwd[0][:0]).dtype
        with record_function("3dgs.raster_backward"):
            buffers = _backward_kernel(
                *ctx.args,
                *ctx.fwd,
                _numpy(grad_image, dt),
                _numpy(grad_T, dt),
                numba.get_num_threads(),
            )
            grads = torch.from_numpy(buffers).sum(0)
        if ctx.abs_grad is not None:
            ctx.abs_grad += grads[:, 6:8].to(ctx.abs_grad)
        d_means, d_conics, d_opac = ctx.in_dtypes
        return (
            grads[:, 0:2].to(d_means),
            grads[:, 2:5].to(d_conics),
            grads[:, 5].to(d_opac),
            grads[:, GRAD_COLUMNS:],
            None,
            None,
            None,
            None,
            None,
            None,
        )


def rasterize_features(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    radii: Tensor,
    depths: Tensor,
    width: int,
    height: int,
    abs_grad: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """F(p) = sum_i T_i alpha_i f_i and T_final(p) over depth-sorted splats, differentiable.

    means2d (G, 2), conics (G, 3), opacities (G,), features (G, D), radii (G,) (0 = culled),
    depths (G,) -> image (H, W, D), transmittance (H, W). The numba kernels run on CPU tensors;
    other devices use the vectorised torch version `rasterize_torch.rasterize_features_torch`.
    `abs_grad` (G, 2), if given, receives in the backward sum_p |dL_p/dmu'| per splat (the
    absolute per-pixel mean gradients that AbsGS densifies by; Ye et al. 2024, Sec. 4.2)."""
    if means2d.device.type != "cpu":
        from recon.gaussians.rasterize_torch import rasterize_features_torch

        return rasterize_features_torch(
            means2d, conics, opacities, features, radii, depths, width, height, abs_grad
        )
    with record_function("3dgs.bin"):
        tile = tile_size(width, height)
        bounds = tile_bounds(means2d, radii, width, height, tile, conics, opacities)
        tile_start, gauss_ids = bin_gaussians(bounds, depths, width, height, tile)
    return _RasterizeFeatures.apply(
        means2d, conics, opacities, features, tile_start, gauss_ids, width, height, tile, abs_grad
    )
