"""Tile binning: each splat is listed in every 16x16 tile its 3-sigma box touches, and the
lists are ordered by (tile, depth) (Kerbl et al. 2023, Sec. 6).

Two twins produce the same `tile_start` / `gauss_ids`:
- `bin_gaussians_sorted`: the reference's one global sort of (tile, depth-rank) keys, pure torch
  (any device);
- `bin_gaussians`: a stable depth argsort followed by a stable counting sort on the tile id
  (one radix pass over the tile digits, O(intersections)) in numba, for the CPU.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

TILE = 16


def tile_grid(width: int, height: int, tile: int = TILE) -> tuple[int, int]:
    """(tiles_x, tiles_y) = (ceil(W / tile), ceil(H / tile))."""
    return (width + tile - 1) // tile, (height + tile - 1) // tile


def tile_bounds(
    means2d: Tensor, radii: Tensor, width: int, height: int, tile: int = TILE
) -> Tensor:
    """Tiles overlapped by the box [mu - r, mu + r]^2: (G, 4) int64 (tx0, ty0, tx1, ty1), ends
    exclusive, clipped to the grid; empty (tx0 == tx1) for culled splats (r = 0).

    means2d (G, 2) pixels, radii (G,). Example: mu = (20, 5), r = 3 at tile 16 -> (1, 0, 2, 1).
    """
    tiles_x, tiles_y = tile_grid(width, height, tile)
    m, r = means2d.detach(), radii.detach()[:, None]
    grid = torch.tensor([tiles_x, tiles_y], device=m.device, dtype=m.dtype)
    # Clamp in floating point first: a huge splat must not overflow the integer cast.
    lo = torch.minimum(torch.floor((m - r) / tile).clamp_min(0), grid)
    hi = torch.minimum(torch.floor((m + r) / tile).clamp_min(-1) + 1, grid)
    hi = torch.where(r > 0, hi, lo)
    return torch.cat([lo, hi], -1).long()


def bin_gaussians_sorted(
    bounds: Tensor, depths: Tensor, width: int, height: int, tile: int = TILE
) -> tuple[Tensor, Tensor]:
    """Reference binning by one global sort of key = tile_id * G + depth_rank.

    bounds (G, 4) from `tile_bounds`, depths (G,) -> tile_start (T + 1,) int64 (tile t's list is
    gauss_ids[tile_start[t]:tile_start[t+1]]) and gauss_ids (N,) int64, front to back per tile.
    """
    tiles_x, tiles_y = tile_grid(width, height, tile)
    G, device = depths.shape[0], depths.device
    span_x, span_y = bounds[:, 2] - bounds[:, 0], bounds[:, 3] - bounds[:, 1]
    counts = (span_x * span_y).clamp_min(0)
    gid = torch.repeat_interleave(torch.arange(G, device=device), counts)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(gid.shape[0], device=device) - first[gid]
    tx = bounds[gid, 0] + local % span_x[gid]
    ty = bounds[gid, 1] + torch.div(local, span_x[gid], rounding_mode="floor")
    rank = torch.empty(G, dtype=torch.long, device=device)
    rank[torch.argsort(depths.detach(), stable=True)] = torch.arange(G, device=device)
    tile_id = ty * tiles_x + tx
    order = torch.argsort(tile_id * G + rank[gid])
    bins = torch.arange(tiles_x * tiles_y + 1, device=device)
    return torch.searchsorted(tile_id[order], bins), gid[order]


@numba.njit(cache=True)
def _counting_sort(order: np.ndarray, bounds: np.ndarray, tiles_x: int, n_tiles: int):
    starts = np.zeros(n_tiles + 1, np.int64)
    for g in order:
        for ty in range(bounds[g, 1], bounds[g, 3]):
            for tx in range(bounds[g, 0], bounds[g, 2]):
                starts[ty * tiles_x + tx + 1] += 1
    for t in range(n_tiles):
        starts[t + 1] += starts[t]
    ids = np.empty(starts[n_tiles], np.int64)
    fill = starts[:n_tiles].copy()
    for g in order:  # depth order, so every tile's list comes out front to back
        for ty in range(bounds[g, 1], bounds[g, 3]):
            for tx in range(bounds[g, 0], bounds[g, 2]):
                t = ty * tiles_x + tx
                ids[fill[t]] = g
                fill[t] += 1
    return starts, ids


def bin_gaussians(
    bounds: Tensor, depths: Tensor, width: int, height: int, tile: int = TILE
) -> tuple[Tensor, Tensor]:
    """Same result as `bin_gaussians_sorted` (CPU): stable depth argsort of the listed splats,
    then a stable counting sort by tile id. bounds (G, 4), depths (G,) -> tile_start, gauss_ids.
    """
    tiles_x, tiles_y = tile_grid(width, height, tile)
    listed = torch.nonzero((bounds[:, 2] > bounds[:, 0]) & (bounds[:, 3] > bounds[:, 1]))[:, 0]
    order = listed[torch.argsort(depths.detach()[listed], stable=True)]
    starts, ids = _counting_sort(order.numpy(), bounds.numpy(), tiles_x, tiles_x * tiles_y)
    return torch.from_numpy(starts), torch.from_numpy(ids)
