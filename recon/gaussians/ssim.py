"""SSIM for the training loss (Wang et al. 2004, "Image Quality Assessment: From Error
Visibility to Structural Similarity", Eq. 13) with a separable blur and a hand-derived backward;
the same value as `pytorch_msssim.ssim` (11-tap Gaussian, sigma 1.5, valid windows, K = (0.01,
0.03)), its twin in the tests, at a fraction of the cost. On a CPU, numba kernels: the L1 +
SSIM loss forward + backward measured 17 -> 4.4 ms at 200x200 and 336 -> 77 ms at 800x800 (CPU
time, one shared core). Elsewhere (CUDA), torch with the five blurred maps in one pair of
grouped convolutions each way: ~55 torch calls a step (forward and backward) against
pytorch_msssim's ~100, whose launches are what a GPU step of 3dgs waits for.

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


_WEIGHTS: dict[tuple, tuple[Tensor, Tensor]] = {}


def _blur_weights(channels: int, like: Tensor) -> tuple[Tensor, Tensor]:
    """The separable blur's grouped-convolution weights for `channels` maps on `like`'s device
    and dtype, (channels, 1, K, 1) and (channels, 1, 1, K): made once, then resident there."""
    key = (channels, like.device, like.dtype)
    if key not in _WEIGHTS:
        taps = torch.from_numpy(gaussian_taps()).to(device=like.device, dtype=like.dtype)
        column = taps.reshape(1, 1, WINDOW, 1).repeat(channels, 1, 1, 1)
        _WEIGHTS[key] = column, column.reshape(channels, 1, 1, WINDOW)
    return _WEIGHTS[key]


def blur_valid(maps: Tensor) -> Tensor:
    """`_blur_valid` in torch: (N, H, W) -> (N, H - K + 1, W - K + 1), columns then rows."""
    column, row = _blur_weights(len(maps), maps)
    out = torch.nn.functional.conv2d(maps[None], column, groups=len(maps))
    return torch.nn.functional.conv2d(out, row, groups=len(maps))[0]


def blur_transpose(maps: Tensor) -> Tensor:
    """`_blur_transpose` in torch, the adjoint of `blur_valid`: (N, h, w) -> (N, h + K - 1,
    w + K - 1)."""
    column, row = _blur_weights(len(maps), maps)
    out = torch.nn.functional.conv_transpose2d(maps[None], row, groups=len(maps))
    return torch.nn.functional.conv_transpose2d(out, column, groups=len(maps))[0]


class _SsimTorch(torch.autograd.Function):
    """The numba pair's algebra in torch ops (any device): the same maps and gradients."""

    @staticmethod
    def forward(ctx, x, y):
        C = len(x)
        m, n, bxx, byy, bxy = blur_valid(torch.cat([x, y, x * x, y * y, x * y])).split(C)
        mn, a2 = m * n, m * m + n * n + K1**2
        b2 = bxx + byy - a2 + (K1**2 + K2**2)  # s_xx + s_yy + C2
        A = (2 * mn + K1**2) / a2
        B = (2 * (bxy - mn) + K2**2) / b2
        ctx.save_for_backward(x, y, m, n, A, B, a2, b2)
        return (A * B).mean()

    @staticmethod
    def backward(ctx, grad):
        x, y, m, n, A, B, a2, b2 = ctx.saved_tensors
        scale = grad / m.numel()
        g_xx = -A * B / b2
        g_xy = 2 * A / b2
        g_m = 2 * B * (n - A * m) / a2 - 2 * m * g_xx - n * g_xy  # s_xx, s_xy depend on m too
        t_m, t_xx, t_xy = blur_transpose(torch.cat([g_m, g_xx, g_xy]) * scale).split(len(x))
        return t_m + 2 * x * t_xx + y * t_xy, None


def ssim(x: Tensor, y: Tensor) -> Tensor:
    """Mean SSIM of images x, y (C, H, W) in [0, 1], H, W >= 11; differentiable in x only.
    CPU tensors use the numba kernels; other devices the same algebra in torch ops."""
    if not devices.uses_cpu_kernels(x):
        return _SsimTorch.apply(x, y.detach())
    return _Ssim.apply(x, y.detach())
