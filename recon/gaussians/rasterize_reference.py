"""Slow, obviously-correct twin of `rasterize.py`: every pixel against every splat, in pure
torch with autograd (any device). Memory is O(H W G): for tests and small renders.

For pixel p and splats sorted by depth (stable), with splat i listed in p's tile:
    alpha_i = min(0.99, o_i exp(-0.5 d^T conic_i d)), d = mu_i - p, set to 0 when < 1/255,
    T_i = prod_{j<i} (1 - alpha_j); the first i with T_i (1 - alpha_i) < 1e-4 and every later
    splat are dropped; F(p) = sum_i T_i alpha_i f_i, T_final = prod_i (1 - alpha_i).
"""

from __future__ import annotations

import torch
from torch import Tensor

from recon.cameras.rays import pixel_centers
from recon.gaussians.alpha import ALPHA_MAX, ALPHA_MIN, T_MIN
from recon.gaussians.tiles import tile_bounds, tile_size
from recon.volrend.volrend import alpha_compositing


def splat_alphas(means2d: Tensor, conics: Tensor, opacities: Tensor, pixels: Tensor) -> Tensor:
    """alpha = min(0.99, o exp(power)), power = -0.5 (a dx^2 + c dy^2) - b dx dy, zeroed where
    power > 0 or alpha < 1/255.  means2d (G, 2), conics (G, 3), opacities (G,), pixels (P, 2)
    -> (P, G)."""
    d = means2d[None] - pixels[:, None]
    dx, dy = d[..., 0], d[..., 1]
    a, b, c = conics.unbind(-1)
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    alpha = torch.clamp(opacities * torch.exp(power), max=ALPHA_MAX)
    keep = (power <= 0) & (alpha >= ALPHA_MIN)
    return torch.where(keep, alpha, torch.zeros_like(alpha))


def composite_alphas(alpha: Tensor, features: Tensor) -> tuple[Tensor, Tensor]:
    """Front-to-back compositing with early termination (`volrend.alpha_compositing`, the one
    compositing primitive).  alpha (P, G) depth-sorted, features (G, D) -> F (P, D), T_final (P,)."""
    weights, alpha = alpha_compositing(alpha, t_min=T_MIN)
    return weights @ features, torch.exp(torch.log1p(-alpha).sum(-1))


def rasterize_features_reference(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    radii: Tensor,
    depths: Tensor,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """Dense twin of `rasterize.rasterize_features`: same arguments, same outputs
    image (H, W, D), transmittance (H, W)."""
    order = torch.argsort(depths.detach(), stable=True)
    order = order[radii[order] > 0]
    tile = tile_size(width, height)
    bounds = tile_bounds(means2d, radii, width, height, tile)[order]
    pixels = pixel_centers(width, height, device=means2d.device, dtype=means2d.dtype).reshape(-1, 2)
    tile_xy = torch.div(pixels.detach(), tile, rounding_mode="floor").long()
    listed = (
        (tile_xy[:, None, 0] >= bounds[:, 0])
        & (tile_xy[:, None, 0] < bounds[:, 2])
        & (tile_xy[:, None, 1] >= bounds[:, 1])
        & (tile_xy[:, None, 1] < bounds[:, 3])
    )
    alpha = splat_alphas(means2d[order], conics[order], opacities[order], pixels)
    alpha = torch.where(listed, alpha, torch.zeros_like(alpha))
    image, T = composite_alphas(alpha, features[order])
    return image.reshape(height, width, -1), T.reshape(height, width)
