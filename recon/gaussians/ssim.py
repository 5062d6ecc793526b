"""SSIM for the training loss with a numba separable blur and a hand-derived backward; the
same value as `pytorch_msssim.ssim` (11-tap Gaussian, sigma 1.5, valid windows, K = (0.01,
0.03)), its twin in the tests, at a fraction of the cost: the L1 + SSIM loss forward + backward
measured 17 -> 4.4 ms at 200x200 and 336 -> 77 ms at 800x800 (CPU time, one shared core).

Per channel, with m = blur(x), n = blur(y), s_xx = blur(x^2) - m^2, s_yy = blur(y^2) - n^2,
s_xy = blur(xy) - m n:  SSIM = mean A B,  A = (2 m n + C1) / (m^2 + n^2 + C1),
B = (2 s_xy + C2) / (s_xx + s_yy + C2). Backward (y is a constant target):
    dA/dm = 2 (n - A m) / (m^2 + n^2 + C1),  dB/ds_xy = 2 / b2,  dB/ds_xx = -B / b2,
    dx = blur^T(g_m - 2 m g_xx - n g_xy) + 2 x blur^T(g_xx) + y blur^T(g_xy).
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from numba import prange
from torch import Tensor

from recon import devices

WINDOW = 11
SIGMA = 1.5
K1, K2 = 0.01, 0.03


def gaussian_taps(size: int = WINDOW, sigma: float = SIGMA) -> np.ndarray:
    """Normalised 1-D Gaussian taps exp(-k^2 / 2 sigma^2), k = -size//2 .. size//2."""
    k = np.arange(size) - size // 2
    taps = np.exp(-(k**2) / (2 * sigma**2))
    return taps / taps.sum()


@numba.njit(parallel=True, cache=True)
def _blur_valid(x, taps):
    """(C, H, W) -> (C, H - K + 1, W - K + 1): rows, then columns (plain loops vectorise)."""
    C, H, W = x.shape
    K = taps.shape[0]
    h, w = H - K + 1, W - K + 1
    out = np.zeros((C, h, w), x.dtype)
    for job in prange(C * h):
        c, i = job // h, job % h
        row = np.zeros(W, x.dtype)
        for k in range(K):
            for j in range(W):
                row[j] += taps[k] * x[c, i + k, j]
        for k in range(K):
            for j in range(w):
                out[c, i, j] += taps[k] * row[j + k]
    return out


@numba.njit(parallel=True, cache=True)
def _blur_transpose(g, taps):
    """Adjoint of `_blur_valid`: (C, h, w) -> (C, h + K - 1, w + K - 1) ('full' correlation)."""
    C, h, w = g.shape
    K = taps.shape[0]
    H, W = h + K - 1, w + K - 1
    out = np.zeros((C, H, W), g.dtype)
    for job in prange(C * H):
        c, i = job // H, job % H
        row = np.zeros(w, g.dtype)
        for k in range(max(0, i - h + 1), min(K, i + 1)):  # output rows i - k that read row i
            for j in range(w):
                row[j] += taps[k] * g[c, i - k, j]
        for k in range(K):
            for j in range(w):
                out[c, i, j + k] += taps[k] * row[j]
    return out


@numba.njit(parallel=True, cache=True)
def _ssim_maps(m, n, bxx, byy, bxy, c1, c2, scale):
    """SSIM sum and the per-window gradients (g_m, g_xx, g_xy) of scale * sum A B."""
    total = 0.0
    g_m, g_xx, g_xy = np.empty_like(m), np.empty_like(m), np.empty_like(m)
    C, h, w = m.shape
    for job in prange(C * h):
        c, i = job // h, job % h
        for j in range(w):
            mm, nn = m[c, i, j], n[c, i, j]
            sxx, syy, sxy = bxx[c, i, j] - mm * mm, byy[c, i, j] - nn * nn, bxy[c, i, j] - mm * nn
            a2, b2 = mm * mm + nn * nn + c1, sxx + syy + c2
            A, B = (2 * mm * nn + c1) / a2, (2 * sxy + c2) / b2
            total += A * B
            gA, gsxx, gsxy = (
                scale * B * 2 * (nn - A * mm) / a2,
                -scale * A * B / b2,
                scale * A * 2 / b2,
            )
            g_m[c, i, j] = gA - 2 * mm * gsxx - nn * gsxy  # s_xx and s_xy also depend on m
            g_xx[c, i, j], g_xy[c, i, j] = gsxx, gsxy
    return total, g_m, g_xx, g_xy


class _Ssim(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, y):
        xs, ys = x.detach().contiguous().numpy(), y.detach().contiguous().numpy()
        taps = gaussian_taps().astype(xs.dtype)
        m, n = _blur_valid(xs, taps), _blur_valid(ys, taps)
        bxx, byy, bxy = (
            _blur_valid(xs * xs, taps),
            _blur_valid(ys * ys, taps),
            _blur_valid(xs * ys, taps),
        )
        scale = 1.0 / m.size
        total, g_m, g_xx, g_xy = _ssim_maps(m, n, bxx, byy, bxy, K1**2, K2**2, scale)
        ctx.saved = (xs, ys, taps, g_m, g_xx, g_xy)
        return x.new_tensor(total * scale)

    @staticmethod
    def backward(ctx, grad):
        xs, ys, taps, g_m, g_xx, g_xy = ctx.saved
        dx = (
            _blur_transpose(g_m, taps)
            + 2 * xs * _blur_transpose(g_xx, taps)
            + ys * _blur_transpose(g_xy, taps)
        )
        return grad * torch.from_numpy(dx), None


def ssim(x: Tensor, y: Tensor) -> Tensor:
    """Mean SSIM of images x, y (C, H, W) in [0, 1], H, W >= 11; differentiable in x only.
    CPU tensors use the numba kernels; other devices `pytorch_msssim.ssim`."""
    if not devices.uses_cpu_kernels(x):
        import pytorch_msssim

        return pytorch_msssim.ssim(
            x[None], y[None], data_range=1.0, size_average=True, win_size=WINDOW, win_sigma=SIGMA
        )
    return _Ssim.apply(x, y.detach())
