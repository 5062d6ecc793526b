"""Image metrics on held-out views: PSNR, SSIM and depth errors (SSIM: Wang et al. 2004).

Images are (..., H, W, 3) in [0, max_val]; leading dims are a batch and give one value per image.
None of these measures geometry: pair them with `recon.metrics.geometry`.
"""

from __future__ import annotations

import math

import numpy as np
import pytorch_msssim
import torch
from torch import Tensor

SSIM_WINDOW = 11  # Gaussian window size of Wang et al. 2004, used by every NeRF/3DGS paper
SSIM_SIGMA = 1.5


def _as_tensor(x) -> Tensor:
    return x if isinstance(x, Tensor) else torch.as_tensor(np.asarray(x))


LOG_MSE_FLOOR = 1e-10  # training logs cap PSNR at 100 dB (for MAX = 1) so the value stays finite


def psnr_from_mse(mse, max_val: float = 1.0):
    """PSNR = 10 log10(MAX^2 / MSE) from a mean squared error (float or tensor): the one PSNR
    formula of the package. +inf at MSE = 0."""
    if isinstance(mse, Tensor):
        return 10.0 * torch.log10(max_val**2 / mse)
    return math.inf if mse <= 0 else 10.0 * math.log10(max_val**2 / mse)


def training_psnr(mse: float | Tensor) -> float | Tensor:
    """PSNR of a training step or a quick held-out check, for the logs: finite (<= 100 dB). A
    tensor MSE gives a detached 0-d float64 tensor on its device (no host sync)."""
    if isinstance(mse, Tensor):
        return psnr_from_mse(mse.detach().double().clamp_min(LOG_MSE_FLOOR))
    return psnr_from_mse(max(float(mse), LOG_MSE_FLOOR))


def psnr(pred, target, max_val: float = 1.0) -> Tensor:
    """PSNR = 10 log10(MAX^2 / MSE), MSE = mean over H, W and channels (the usual definition).

    pred, target: (..., H, W, 3) arrays or tensors. Returns (...,) float64; +inf when
    the images are identical. Example: a constant offset e gives PSNR = -20 log10(e / MAX).
    """
    pred, target = _as_tensor(pred).double(), _as_tensor(target).double()
    if pred.shape != target.shape:
        raise ValueError(f"psnr: shapes differ, {tuple(pred.shape)} vs {tuple(target.shape)}")
    mse = (pred - target).square().mean(dim=(-3, -2, -1))
    return psnr_from_mse(mse, max_val)  # mse = 0 -> +inf, as it should


def psnr_masked(pred, target, mask, max_val: float = 1.0) -> Tensor:
    """PSNR over the pixels where `mask` (..., H, W) is true: MSE = mean over those pixels and
    the channels. With an all-true mask it equals `psnr`. Returns (...,) float64."""
    pred, target = _as_tensor(pred).double(), _as_tensor(target).double()
    if pred.shape != target.shape:
        raise ValueError(f"psnr: shapes differ, {tuple(pred.shape)} vs {tuple(target.shape)}")
    w = _as_tensor(mask).to(device=pred.device, dtype=torch.float64).expand(pred.shape[:-1])
    mse = ((pred - target).square().mean(-1) * w).sum((-2, -1)) / w.sum((-2, -1))
    return psnr_from_mse(mse, max_val)


def border_mask(height: int, width: int, fraction: float) -> Tensor:
    """(H, W) bool: pixels within `fraction` of the image's height of its top or bottom edge, or
    within `fraction` of its width of its left or right edge - the outer band of a photo, where
    an unbounded capture's far background shows. Example: 20 x 10 at 0.15 -> rows 0-2 and
    17-19, columns 0-1 and 8-9 (the band is rounded to whole pixels, at least one)."""
    by, bx = max(1, round(fraction * height)), max(1, round(fraction * width))
    rows, cols = torch.arange(height), torch.arange(width)
    row_in = (rows < by) | (rows >= height - by)
    col_in = (cols < bx) | (cols >= width - bx)
    return row_in[:, None] | col_in[None, :]


def ssim(pred, target, max_val: float = 1.0) -> Tensor:
    """SSIM (Wang et al. 2004) with the 11x11 Gaussian window, sigma = 1.5, K = (0.01, 0.03).

    SSIM = mean over valid window positions and channels of
    (2 mu_x mu_y + C1)(2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(s_x^2 + s_y^2 + C2)),
    C1 = (0.01 MAX)^2, C2 = (0.03 MAX)^2, computed by `pytorch_msssim` (the maintained
    implementation; windows do not cross the border, as in skimage with the same settings).
    pred, target: (..., H, W, 3) with H, W >= 11. Returns (...,) in the input's float dtype.
    """
    pred, target = _as_tensor(pred), _as_tensor(target)
    if pred.shape != target.shape:
        raise ValueError(f"ssim: shapes differ, {tuple(pred.shape)} vs {tuple(target.shape)}")
    if min(pred.shape[-3:-1]) < SSIM_WINDOW:
        raise ValueError(f"ssim: images must be at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels")
    dtype = pred.dtype if pred.is_floating_point() else torch.float32
    batch = pred.shape[:-3]
    x = pred.to(dtype).reshape(-1, *pred.shape[-3:]).permute(0, 3, 1, 2)  # (B, 3, H, W)
    y = target.to(dtype).reshape(-1, *target.shape[-3:]).permute(0, 3, 1, 2)
    value = pytorch_msssim.ssim(
        x,
        y,
        data_range=max_val,
        size_average=False,
        win_size=SSIM_WINDOW,
        win_sigma=SSIM_SIGMA,
        K=(0.01, 0.03),
    )
    return value.reshape(batch)


def depth_errors(pred_depth, gt_depth, mask=None) -> dict[str, float]:
    """Depth errors over valid pixels (Eigen et al. 2014 conventions).

    abs_rel = mean(|d - d*| / d*),  rmse = sqrt(mean((d - d*)^2)),
    delta_1.25 = fraction of pixels with max(d / d*, d* / d) < 1.25.
    pred_depth, gt_depth: (..., H, W) z-depths in the same units; mask: (..., H, W) bool,
    defaulting to pixels where the ground truth is finite and positive (the mask is always
    intersected with that, since abs_rel divides by d*). Returns floats plus `count`, the
    number of pixels used; with no valid pixel every error is NaN.
    """
    pred = _as_tensor(pred_depth).double()
    gt = _as_tensor(gt_depth).double()
    valid = torch.isfinite(gt) & (gt > 0) & torch.isfinite(pred)
    if mask is not None:
        valid &= _as_tensor(mask).to(torch.bool)
    pred, gt = pred[valid], gt[valid]
    if gt.numel() == 0:
        nan = float("nan")
        return {"abs_rel": nan, "rmse": nan, "delta_1.25": nan, "count": 0}
    err = pred - gt
    ratio = torch.maximum(pred / gt, gt / pred.clamp_min(torch.finfo(gt.dtype).tiny))
    return {
        "abs_rel": float((err.abs() / gt).mean()),
        "rmse": float(err.square().mean().sqrt()),
        "delta_1.25": float((ratio < 1.25).double().mean()),
        "count": int(gt.numel()),
    }
