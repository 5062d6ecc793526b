"""Tile binning: each splat is listed in every tile (16 or 32 px square, `tile_size`) its 3-sigma
box touches, and the lists are ordered by (tile, depth) (Kerbl et al. 2023, Sec. 6). Given the splats' conics and
opacities, the box shrinks to the bounding box of the ellipse where alpha can reach 1/255 (the
pixels the rasterizer would visit): on lego at 800 px that drops 2/3 of the tile entries
(653 k -> 232 k) and leaves every image bit-identical.

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

from recon.gaussians.alpha import ALPHA_MIN, SLACK

TILE = 16  # the tile side of small images
TILE_LARGE = 32  # and of images of LARGE_IMAGE pixels or more
LARGE_IMAGE = 384 * 384


def tile_size(width: int, height: int) -> int:
    """The tile side for a width x height image. Per-row work (each splat's span in each row
    of each tile it meets) dominates the rasterizer, and a larger tile splits fewer splats;
    a smaller one terminates more pixels together and spreads small images over the threads.
    Forward on lego, 41.8 k Gaussians, 2 threads (pipelines/bench_render.py's model): 16 vs
    32 px tiles 10.1 vs 16.5 ms at 200 px, 21.8 vs 20.0 at 400, 38.7 vs 32.6 at 600, 56.5
    vs 49.1 ms at 800 px."""
    return TILE_LARGE if width * height >= LARGE_IMAGE else TILE


def tile_grid(width: int, height: int, tile: int) -> tuple[int, int]:
    """(tiles_x, tiles_y) = (ceil(W / tile), ceil(H / tile))."""
    return (width + tile - 1) // tile, (height + tile - 1) // tile


def alpha_extent(conics: Tensor, opacities: Tensor) -> Tensor:
    """Half sides (G, 2) of the box around the ellipse where alpha = o exp(-d^T conic d / 2) can
    reach 1/255: d^T conic d <= q, q = -2 ln(255^-1 / o) widened by SLACK as the rasterizer's
    own pixel culling is (so no pixel it would draw falls outside), half sides sqrt(q C / det),
    sqrt(q A / det) for conic (A, B, C), det = AC - B^2; inf for a conic that is not positive
    definite, -1 for o < 1/255 (nothing to draw). conics (G, 3), opacities (G,).
    Example: conic (1, 0, 4), o = 1 -> q = 2 ln 255 (1 + SLACK) + 2 SLACK, half sides
    (sqrt(q), sqrt(q) / 2) = (3.3310, 1.6655)."""
    A, B, C = conics.detach().double().unbind(-1)
    o = opacities.detach().double()
    q = (2.0 * SLACK - 2.0 * (1.0 + SLACK) * torch.log(ALPHA_MIN / o)).clamp_min(0.0)
    det = A * C - B * B
    definite = (A > 0) & (det > 0)
    half = torch.stack([q * C, q * A], -1) / torch.where(definite, det, 1.0)[:, None]
    half = torch.where(definite[:, None], half.clamp_min(0.0).sqrt(), torch.inf)
    return torch.where((o >= ALPHA_MIN)[:, None], half, -1.0)


def tile_bounds(
    means2d: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    tile: int,
    conics: Tensor | None = None,
    opacities: Tensor | None = None,
) -> Tensor:
    """Tiles overlapped by the box [mu - r, mu + r]^2, or with conics (G, 3) and opacities (G,)
    by its intersection with the `alpha_extent` box around the pixel centres the splat can
    reach: (G, 4) int64 (tx0, ty0, tx1, ty1), ends exclusive, clipped to the grid; empty
    (tx0 == tx1) for culled splats (r = 0) and for o < 1/255.

    means2d (G, 2) pixels, radii (G,). Example: mu = (20, 5), r = 3, tile 16 -> (1, 0, 2, 1).
    """
    tiles_x, tiles_y = tile_grid(width, height, tile)
    m, r = means2d.detach(), radii.detach()[:, None]
    grid = torch.tensor([tiles_x, tiles_y], device=m.device, dtype=m.dtype)
    # Clamp in floating point first: a huge splat must not overflow the integer cast.
    lo = torch.minimum(torch.floor((m - r) / tile).clamp_min(0), grid)
    hi = torch.minimum(torch.floor((m + r) / tile).clamp_min(-1) + 1, grid)
    hi = torch.where(r > 0, hi, lo)
    if conics is not None:
        # the tiles of pixel centres c + 0.5 in [mu - e, mu + e], in float64, e widened by a
        # hair more than float32 rounding so the rasterizer's own (float32) bound stays inside
        e, m64 = alpha_extent(conics, opacities), m.double()
        e = torch.where(e >= 0, e * (1 + 1e-5) + 1e-5, e)
        lo_e = torch.floor((m64 - e - 0.5) / tile).to(lo.dtype)
        hi_e = torch.floor((m64 + e - 0.5) / tile).to(lo.dtype) + 1
        reach = e >= 0
        lo = torch.where(reach, torch.maximum(lo, lo_e), lo)
        hi = torch.where(reach, torch.minimum(hi, hi_e), lo)
        hi = torch.maximum(hi, lo)
    return torch.cat([lo, hi], -1).long()


def bin_gaussians_sorted(
    bounds: Tensor, depths: Tensor, width: int, height: int, tile: int
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


RADIX_BITS = 11


@numba.njit(cache=True)
def _radix_argsort(keys: np.ndarray) -> np.ndarray:
    """Stable argsort of unsigned integer keys (N,): least-significant-digit radix sort,
    RADIX_BITS per pass, the keys carried along with the indices."""
    n, bits = keys.shape[0], keys.itemsize * 8
    idx, keys = np.arange(n), keys.copy()
    idx_out, keys_out = np.empty_like(idx), np.empty_like(keys)
    mask = (1 << RADIX_BITS) - 1
    for shift in range(0, bits, RADIX_BITS):
        count = np.zeros(mask + 2, np.int64)
        for i in range(n):
            count[((keys[i] >> shift) & mask) + 1] += 1
        for d in range(mask + 1):
            count[d + 1] += count[d]
        for i in range(n):
            d = (keys[i] >> shift) & mask
            idx_out[count[d]], keys_out[count[d]] = idx[i], keys[i]
            count[d] += 1
        idx, idx_out, keys, keys_out = idx_out, idx, keys_out, keys
    return idx


def stable_argsort(values: np.ndarray) -> np.ndarray:
    """np/torch `argsort(stable=True)` of float32/float64 values by a radix sort of their
    bits mapped to unsigned integers of the same order (the sign bit flipped for values >= 0,
    every bit for negative ones). Ties keep index order. NaNs with the sign bit clear sort
    after +inf, as in torch. (N,) -> (N,) int64."""
    unsigned = {4: np.uint32, 8: np.uint64}[values.itemsize]
    bits = np.ascontiguousarray(values).view(unsigned)
    sign = unsigned(1) << unsigned(values.itemsize * 8 - 1)
    return _radix_argsort(np.where(bits & sign, ~bits, bits | sign))


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
    bounds: Tensor, depths: Tensor, width: int, height: int, tile: int
) -> tuple[Tensor, Tensor]:
    """Same result as `bin_gaussians_sorted` (CPU): stable depth argsort of the listed splats,
    then a stable counting sort by tile id. bounds (G, 4), depths (G,) -> tile_start, gauss_ids.
    """
    tiles_x, tiles_y = tile_grid(width, height, tile)
    listed = torch.nonzero((bounds[:, 2] > bounds[:, 0]) & (bounds[:, 3] > bounds[:, 1]))[:, 0]
    order = listed[torch.from_numpy(stable_argsort(depths.detach()[listed].numpy()))]
    starts, ids = _counting_sort(order.numpy(), bounds.numpy(), tiles_x, tiles_x * tiles_y)
    return torch.from_numpy(starts), torch.from_numpy(ids)
