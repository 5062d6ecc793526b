"""The 3D smoothing filter of Mip-Splatting (Yu et al. 2024, "Mip-Splatting: Alias-free 3D
Gaussian Splatting", Sec. 5.1, Eqs. 8-10).

A training camera that sees a point at depth d samples the scene there every d / f world units
(f the focal length in pixels), so no detail finer than the densest such sampling over the
training views, T = min_n d_n / f_n, is constrained by the photos (Eq. 8). Each Gaussian is
convolved with an isotropic Gaussian of variance s2 T^2 (Eq. 9): the covariance becomes
Sigma + s2 T^2 I, and the opacity is scaled by sqrt(|Sigma| / |Sigma + s2 T^2 I|) so that the
filtered Gaussian keeps the unfiltered one's integral (Eq. 10). Sigma = R S^2 R^T, so the
filter adds s2 T^2 to each squared scale and leaves the rotation alone.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from recon.cameras import Cameras


@torch.no_grad()
def sampling_intervals(
    means: Tensor, cameras: Cameras, margin: float = 0.15, near: float = 0.01
) -> Tensor:
    """means (G, 3) world, C `cameras` -> T (G,): the smallest z / fx over the cameras whose
    image, widened by `margin` of its size on each side, holds the projected mean at
    z > `near` (the Gaussian's finest training sampling interval, Mip-Splatting Eq. 8). A mean
    no camera sees takes the largest interval of those seen (as the paper's code does); with
    none seen at all, ones. Example: cameras 2 and 4 units in front of a point, fx = 100 ->
    T = 0.02."""
    big = torch.finfo(means.dtype).max
    best = torch.full(means.shape[:1], big, dtype=means.dtype, device=means.device)
    sizes = zip(cameras.width.tolist(), cameras.height.tolist(), strict=True)
    for M, k, (width, height) in zip(cameras.cam_from_world, cameras.K, sizes, strict=True):
        M, k = M.to(means), k.to(means)
        x = means @ M[:3, :3].T + M[:3, 3]
        z = x[:, 2]
        zs = z.clamp_min(near)
        u = k[0, 0] * x[:, 0] / zs + k[0, 2]
        v = k[1, 1] * x[:, 1] / zs + k[1, 2]
        seen = (
            (z > near)
            & (u >= -margin * width)
            & (u <= (1 + margin) * width)
            & (v >= -margin * height)
            & (v <= (1 + margin) * height)
        )
        best = torch.where(seen, torch.minimum(best, zs / k[0, 0]), best)
    unseen = best == big
    if unseen.all():
        return torch.ones_like(best)
    return torch.where(unseen, best[~unseen].max(), best)


def smoothed(
    log_scales: Tensor, opacity_logits: Tensor, intervals: Tensor, variance_scale: float
) -> tuple[Tensor, Tensor]:
    """log_scales (G, 3), opacity_logits (G,) or (G, 1), intervals T (G,) -> the same after the
    3D filter of variance `variance_scale` * T^2 (Mip-Splatting Eqs. 9-10; the paper's 0.2):
    scales sqrt(s^2 + v), opacity sigmoid(o) * sqrt(prod s^2 / prod (s^2 + v)) as a logit.
    Differentiable in log_scales and opacity_logits; v = 0 returns them unchanged."""
    var = (variance_scale * intervals**2).to(log_scales)[:, None]
    sq = torch.exp(2 * log_scales)
    filtered_sq = sq + var
    # log sqrt(|Sigma| / |Sigma + v I|) <= 0
    log_coef = (log_scales - 0.5 * torch.log(filtered_sq)).sum(-1)
    log_coef = log_coef.reshape(opacity_logits.shape)
    log_alpha = -F.softplus(-opacity_logits) + log_coef  # log(sigmoid(o) * coef)
    # logit(p) = log p - log(1 - p), with p = exp(log_alpha) < 1
    logits = log_alpha - torch.log(-torch.expm1(log_alpha))
    return 0.5 * torch.log(filtered_sq), logits
