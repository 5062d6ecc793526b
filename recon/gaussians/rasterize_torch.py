"""Vectorised pure-torch tile rasterizer for non-CPU devices: the same semantics as the dense
twin (`rasterize_reference`) but over the (tile, depth)-sorted intersection list, so memory is
O(intersections x 256) instead of O(H W G). Autograd does the backward.

Every intersection (splat i listed in tile t) is evaluated at the 256 pixels of t. Within a
tile's segment of the list, transmittance is a segmented exclusive cumulative sum in log space,
T_i = exp(sum_{j<i} log(1 - alpha_j)) (float64, so subtracting the segment's offset is exact
enough), then the first splat that would take T below 1e-4 and all later ones are dropped and
T recomputed, as in the reference.
"""

from __future__ import annotations

import torch
from torch import Tensor

from recon.gaussians.alpha import ALPHA_MAX, ALPHA_MIN, T_MIN
from recon.gaussians.tiles import bin_gaussians_sorted, tile_bounds, tile_grid, tile_size
from recon.volrend.volrend import alpha_compositing


def _pixel_grid(
    tile_ids: Tensor, width: int, height: int, tile: int, dtype
) -> tuple[Tensor, Tensor, Tensor]:
    """Pixel-centre coordinates (N, tile^2) of the tile of each intersection and their
    validity."""
    tiles_x, _ = tile_grid(width, height, tile)
    slot = torch.arange(tile * tile, device=tile_ids.device)
    px = (tile_ids % tiles_x)[:, None] * tile + slot % tile
    py = torch.div(tile_ids, tiles_x, rounding_mode="floor")[:, None] * tile + slot // tile
    return px.to(dtype) + 0.5, py.to(dtype) + 0.5, (px < width) & (py < height)


def _abs_sum_into(sink: Tensor, column: int, gid: Tensor):
    """A gradient hook on an (N, tile^2) per-pixel offset: adds sum_p |grad| to sink[gid, column]."""

    def hook(grad: Tensor) -> None:
        sink[:, column].index_add_(0, gid, grad.abs().sum(1).to(sink))

    return hook


def _alphas(means2d, conics, opacities, gid, px, py, on_image, abs_grad=None) -> Tensor:
    dx, dy = means2d[gid, 0:1] - px, means2d[gid, 1:2] - py
    if abs_grad is not None and dx.requires_grad:
        # dL/d dx[n, p] is pixel p's share of dL/dmx of intersection n's splat
        dx.register_hook(_abs_sum_into(abs_grad, 0, gid))
        dy.register_hook(_abs_sum_into(abs_grad, 1, gid))
    a, b, c = conics[gid, 0:1], conics[gid, 1:2], conics[gid, 2:3]
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    alpha = torch.clamp(opacities[gid, None] * torch.exp(power), max=ALPHA_MAX)
    keep = on_image & (power <= 0) & (alpha >= ALPHA_MIN)
    return torch.where(keep, alpha, torch.zeros_like(alpha))


def rasterize_features_torch(
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
    """Same arguments and outputs as `rasterize.rasterize_features`: image (H, W, D),
    transmittance (H, W)."""
    tile = tile_size(width, height)
    bounds = tile_bounds(means2d, radii, width, height, tile, conics, opacities)
    starts, gid = bin_gaussians_sorted(bounds, depths, width, height, tile)
    return composite_tile_lists(
        means2d, conics, opacities, features, starts, gid, width, height, tile, abs_grad
    )


def composite_tile_lists(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    tile_start: Tensor,
    gauss_ids: Tensor,
    width: int,
    height: int,
    tile: int,
    abs_grad: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Composite given per-tile lists: splats gauss_ids[tile_start[t]:tile_start[t + 1]] (depth
    order) at the pixels of tile t (row-major tiles of `tile` px) -> image (H, W, D),
    transmittance (H, W)."""
    tiles_x, tiles_y = tile_grid(width, height, tile)
    n_tiles, D = tiles_x * tiles_y, features.shape[1]
    gid = gauss_ids
    tile_ids = torch.repeat_interleave(torch.arange(n_tiles, device=gid.device), tile_start.diff())
    px, py, on_image = _pixel_grid(tile_ids, width, height, tile, means2d.dtype)
    alpha = _alphas(means2d, conics, opacities, gid, px, py, on_image, abs_grad)
    # each of a tile's pixels composites the tile's depth-sorted list: packed along dim 0
    weights, alpha = alpha_compositing(alpha, tile_ids, t_min=T_MIN)
    log1m = torch.log1p(-alpha.double())
    weighted = weights[..., None] * features[gid, None, :]  # (N, tile^2, D)
    image = features.new_zeros(n_tiles, tile * tile, D).index_add(0, tile_ids, weighted)
    log_final = log1m.new_zeros(n_tiles, tile * tile).index_add(0, tile_ids, log1m)
    T_final = torch.exp(log_final).to(alpha.dtype)
    return _untile(image, tiles_x, tiles_y, tile, width, height), _untile(
        T_final[..., None], tiles_x, tiles_y, tile, width, height
    )[..., 0]


def _untile(x: Tensor, tiles_x: int, tiles_y: int, tile: int, width: int, height: int) -> Tensor:
    """(tiles, tile^2, D) -> (H, W, D), dropping the padding of edge tiles."""
    D = x.shape[-1]
    x = x.reshape(tiles_y, tiles_x, tile, tile, D).permute(0, 2, 1, 3, 4)
    return x.reshape(tiles_y * tile, tiles_x * tile, D)[:height, :width]
