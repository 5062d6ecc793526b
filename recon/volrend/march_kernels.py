"""Fast CPU twin of `OccupancyGrid.march_torch` (numba): march every ray at a fixed (or
cone-growing) step and emit ONLY the intervals whose midpoint falls in an occupied cell,
without materialising the dense list of all marching intervals first.

The arithmetic mirrors `occupancy.march_intervals`, `contraction.scene_to_unit_cube` and
`occupancy.cells_of` step for step; `tests/volrend/test_march_kernels.py` checks that both give the
same packed samples.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np
import torch
from torch import Tensor


@numba.njit(cache=True, inline="always")
def warp(t, step, cone, t_far):
    if cone <= 0.0:
        return t / step
    t_sw = step / cone
    t_d = max(t_far, t_sw)
    s = min(t, t_sw) / step + math.log(min(max(t, t_sw), t_d) / t_sw) / cone
    if t > t_d:
        s += (1.0 - t_d / t) / cone
    return s


@numba.njit(cache=True, inline="always")
def unwarp(s, step, cone, t_far):
    if cone <= 0.0:
        return s * step
    t_sw = step / cone
    s_sw = t_sw / step
    if s <= s_sw:
        return s * step
    t_d = max(t_far, t_sw)
    s_d = s_sw + math.log(t_d / t_sw) / cone
    if s <= s_d:
        return t_sw * math.exp((s - s_sw) * cone)
    den = 1.0 - (s - s_d) * cone
    return t_d / den if den > 0.0 else math.inf


@numba.njit(cache=True, inline="always")
def march_interval(k, t_min, t_max, s_min, u, step, cone, t_far):
    """Interval k of a ray's march (`occupancy.march_intervals`): from t_min (k = 0) or the
    unwarped s_min + k - u to the unwarped s_min + k + 1 - u, clipped at t_max."""
    start = t_min if k == 0 else unwarp(s_min + k - u, step, cone, t_far)
    return start, min(unwarp(s_min + k + 1.0 - u, step, cone, t_far), t_max)


@numba.njit(cache=True, inline="always")
def unit_point(o, d, t, lo, hi, unbounded):
    """The point o + t d mapped to the unit cube as `scene_to_unit_cube` does -> (x0, x1, x2);
    x0 = -1 when it falls outside the cube."""
    y0 = 2.0 * (o[0] + t * d[0] - lo[0]) / (hi[0] - lo[0]) - 1.0
    y1 = 2.0 * (o[1] + t * d[1] - lo[1]) / (hi[1] - lo[1]) - 1.0
    y2 = 2.0 * (o[2] + t * d[2] - lo[2]) / (hi[2] - lo[2]) - 1.0
    if unbounded:
        n = math.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
        if n > 1.0:
            f = (2.0 - 1.0 / n) / n
            y0, y1, y2 = y0 * f, y1 * f, y2 * f
        x0, x1, x2 = 0.25 * y0 + 0.5, 0.25 * y1 + 0.5, 0.25 * y2 + 0.5
    else:
        x0, x1, x2 = 0.5 * y0 + 0.5, 0.5 * y1 + 0.5, 0.5 * y2 + 0.5
    if x0 < 0.0 or x0 > 1.0 or x1 < 0.0 or x1 > 1.0 or x2 < 0.0 or x2 > 1.0:
        return -1.0, x1, x2
    return x0, x1, x2


@numba.njit(cache=True, inline="always")
def box_affine(o, d, lo, hi):
    """For a bounded box: the unit-cube point of o + t d is a + t b, a = (o - lo) / (hi - lo),
    b = d / (hi - lo) -> (a0, a1, a2, b0, b1, b2). `unit_point` computes the same point with
    three divisions a sample; this is two per axis a ray (the same point up to rounding: a
    sample within ~1e-7 of a cell boundary may fall in the neighbouring cell)."""
    s0, s1, s2 = hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]
    return (
        (o[0] - lo[0]) / s0,
        (o[1] - lo[1]) / s1,
        (o[2] - lo[2]) / s2,
        d[0] / s0,
        d[1] / s1,
        d[2] / s2,
    )


@numba.njit(cache=True, inline="always")
def affine_point(affine, t):
    """a + t b for a ray's `box_affine` coefficients (a0, a1, a2, b0, b1, b2), x0 = -1 outside
    the unit cube, as `unit_point` returns it."""
    a0, a1, a2, b0, b1, b2 = affine
    x0, x1, x2 = a0 + t * b0, a1 + t * b1, a2 + t * b2
    if x0 < 0.0 or x0 > 1.0 or x1 < 0.0 or x1 > 1.0 or x2 < 0.0 or x2 > 1.0:
        return -1.0, x1, x2
    return x0, x1, x2


@numba.njit(cache=True, inline="always")
def ray_unit_point(o, d, t, lo, hi, unbounded, affine):
    """The unit-cube point of o + t d for a march: `unit_point` (the contraction) when
    unbounded, else `affine_point` with the ray's `box_affine` coefficients `affine`."""
    if unbounded:
        return unit_point(o, d, t, lo, hi, True)
    return affine_point(affine, t)


@numba.njit(cache=True, inline="always")
def cell_exit(affine, x0, x1, x2, n):
    """The t at which a bounded ray, unit-cube point a + t b (`box_affine`), leaves the cell of
    an n^3 grid over the unit cube that holds its point x = (x0, x1, x2) (inside the cube):
    the nearest of the three cell faces ahead of it (Amanatides & Woo 1987, "A Fast Voxel
    Traversal Algorithm for Ray Tracing"). Cell i along an axis is min(int(x n), n - 1), as
    `cell_occupied` and `voxel_kernels.lattice_cell` (n = res - 1) find it."""
    a0, a1, a2, b0, b1, b2 = affine
    return min(_face_ahead(a0, b0, x0, n), _face_ahead(a1, b1, x1, n), _face_ahead(a2, b2, x2, n))


@numba.njit(cache=True, inline="always")
def _face_ahead(a, b, x, n):
    """t of the face of x's cell (n cells along the axis, unit-cube point a + t b) that the ray
    crosses next along this axis; inf when the ray runs parallel to it."""
    i = min(int(x * n), n - 1)
    if b > 0.0:
        return ((i + 1) / n - a) / b
    if b < 0.0:
        return (i / n - a) / b
    return math.inf


@numba.njit(cache=True, inline="always")
def last_in_cell(k, t_exit, s_min, u, step, cone, t_far):
    """Empty-space skipping for a march whose interval k has its midpoint in an empty cell
    that the ray leaves at t_exit: the last interval index every interval up to which lies
    before t_exit (interval k' ends at unwarp(s_min + k' + 1 - u) <= t_exit, see
    `march_interval`), so its midpoint is in the same empty cell and the march can resume at
    the returned index + 1 with exactly the samples a step-by-step march keeps. At least k."""
    s = min(warp(t_exit, step, cone, t_far) - s_min + u, 1e18)  # t_exit may be inf
    return max(k, int(math.floor(s)) - 1)  # noqa: RUF046 (numba typing)


@numba.njit(cache=True, inline="always")
def skip_empty(k, x0, x1, x2, affine, coarse, coarse_res, occ, res, s_min, u, spacing):
    """One step of a bounded march through a two-level occupancy (a coarse any-pooled
    bitfield `coarse` over coarse_res^3 cells and the occupancy bitfield occ over res^3): -1
    when interval k's midpoint x is in an occupied cell (the caller samples it), else the
    last interval index that lies in the same empty cell (`last_in_cell`, >= k), taken in
    the coarse cell when that is empty. x outside the unit cube (x0 < 0): k, one step."""
    if x0 < 0.0:
        return k
    step, cone, t_far = spacing
    if not cell_occupied(x0, x1, x2, coarse, coarse_res):
        t_exit = cell_exit(affine, x0, x1, x2, coarse_res)
        return last_in_cell(k, t_exit, s_min, u, step, cone, t_far)
    if not cell_occupied(x0, x1, x2, occ, res):
        return last_in_cell(k, cell_exit(affine, x0, x1, x2, res), s_min, u, step, cone, t_far)
    return -1


@numba.njit(cache=True, inline="always")
def cell_occupied(x0, x1, x2, occ, res):
    """Is the unit-cube point (x0 >= 0: inside) in an occupied cell of the res^3 bitfield?"""
    if x0 < 0.0:
        return False
    i = min(max(int(x0 * res), 0), res - 1)
    j = min(max(int(x1 * res), 0), res - 1)
    k = min(max(int(x2 * res), 0), res - 1)
    return occ[i + res * (j + res * k)]


@numba.njit(cache=True)
def _march_ray(
    r,
    o,
    d,
    t_min,
    t_max,
    step,
    cone,
    t_far,
    u,
    lo,
    hi,
    unbounded,
    occ,
    res,
    cap,
    out_s,
    out_e,
    write,
):
    """Count (write=False) or write the kept intervals of ray r, at most `cap` of them (the
    first ones, front to back; cap <= 0: no limit); returns how many."""
    if not t_max > t_min:
        return 0
    s_min, s_max = warp(t_min, step, cone, t_far), warp(t_max, step, cone, t_far)
    count = int(math.ceil(max(s_max - s_min + u, 0.0)))  # noqa: RUF046 (numba typing)
    count = max(count, 1)
    affine = box_affine(o, d, lo, hi)  # used when not unbounded
    n = 0
    for k in range(count):
        start, end = march_interval(k, t_min, t_max, s_min, u, step, cone, t_far)
        if not end > start:
            continue
        x0, x1, x2 = ray_unit_point(o, d, 0.5 * (start + end), lo, hi, unbounded, affine)
        if cell_occupied(x0, x1, x2, occ, res):
            if write:
                out_s[n] = start
                out_e[n] = end
            n += 1
            if n == cap:
                break
    return n


@numba.njit(parallel=True, cache=True)
def _count(
    origins, dirs, t_min, t_max, step, cone, t_far, u, lo, hi, unbounded, occ, res, cap, counts
):
    dummy = np.empty(0, dtype=origins.dtype)
    for r in numba.prange(origins.shape[0]):
        counts[r] = _march_ray(
            r,
            origins[r],
            dirs[r],
            t_min[r],
            t_max[r],
            step,
            cone,
            t_far,
            u[r],
            lo,
            hi,
            unbounded,
            occ,
            res,
            cap,
            dummy,
            dummy,
            False,
        )


@numba.njit(parallel=True, cache=True)
def _fill(
    origins,
    dirs,
    t_min,
    t_max,
    step,
    cone,
    t_far,
    u,
    lo,
    hi,
    unbounded,
    occ,
    res,
    cap,
    offsets,
    ray_indices,
    starts,
    ends,
):
    for r in numba.prange(origins.shape[0]):
        a = offsets[r]
        b = offsets[r + 1]
        if b > a:
            _march_ray(
                r,
                origins[r],
                dirs[r],
                t_min[r],
                t_max[r],
                step,
                cone,
                t_far,
                u[r],
                lo,
                hi,
                unbounded,
                occ,
                res,
                cap,
                starts[a:b],
                ends[a:b],
                True,
            )
            ray_indices[a:b] = r


def march_occupied(
    origins: Tensor,
    dirs: Tensor,
    t_min: Tensor,
    t_max: Tensor,
    occupied: Tensor,
    resolution: int,
    aabb: Tensor,
    unbounded: bool,
    step: float,
    cone_angle: float = 0.0,
    u: Tensor | None = None,
    max_samples: int = 0,
    disparity_from: float = math.inf,
) -> tuple[Tensor, Tensor, Tensor]:
    """Packed (ray_indices (N,), t_starts (N,), t_ends (N,)) of the occupied marching intervals.

    origins, dirs: (R, 3) CPU float tensors; t_min, t_max: (R,); occupied: (res^3,) bool;
    aabb: (2, 3) scene box; u: (R,) start offsets in [0, 1) or None; max_samples: keep only the
    first max_samples occupied intervals of each ray (0: all); step, cone_angle, disparity_from:
    the spacing of `occupancy.march_intervals`.
    """
    dt = origins.dtype
    o = origins.detach().contiguous().numpy()
    d = dirs.detach().contiguous().numpy()
    tmin = t_min.detach().to(dt).contiguous().numpy()
    tmax = t_max.detach().to(dt).contiguous().numpy()
    uu = (torch.zeros_like(t_min) if u is None else u).detach().to(dt).contiguous().numpy()
    lo = aabb[0].detach().to(dt).contiguous().numpy()
    hi = aabb[1].detach().to(dt).contiguous().numpy()
    occ = occupied.contiguous().numpy()
    counts = np.zeros(o.shape[0], dtype=np.int64)
    spacing = (float(step), float(cone_angle), float(disparity_from))
    _count(
        o,
        d,
        tmin,
        tmax,
        *spacing,
        uu,
        lo,
        hi,
        bool(unbounded),
        occ,
        resolution,
        int(max_samples),
        counts,
    )
    offsets = np.zeros(o.shape[0] + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    n = int(offsets[-1])
    ray_indices = np.empty(n, dtype=np.int64)
    starts = np.empty(n, dtype=o.dtype)
    ends = np.empty(n, dtype=o.dtype)
    _fill(
        o,
        d,
        tmin,
        tmax,
        *spacing,
        uu,
        lo,
        hi,
        bool(unbounded),
        occ,
        resolution,
        int(max_samples),
        offsets,
        ray_indices,
        starts,
        ends,
    )
    return torch.from_numpy(ray_indices), torch.from_numpy(starts), torch.from_numpy(ends)


@functools.lru_cache(maxsize=8)
def tile_order(height: int, width: int, threads: int, tile: int = 8) -> Tensor:
    """The order in which a parallel CPU kernel should take the rays of a height x width image
    (ray y * width + x) -> (height * width,) int64: tile x tile pixel blocks (neighbouring rays
    read the same cells while they are in cache), dealt round-robin to the threads (numba's
    static schedule gives thread i the i-th of `threads` equal runs of the order), so every
    thread gets tiles from all over the image, not one band of it. Lego-200: one band holds
    twice the samples of the other. Do not modify the result: it is cached."""
    y, x = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    tiles_x = -(-width // tile)
    block = (y // tile) * tiles_x + x // tile
    inside = (y % tile) * tile + x % tile
    key = ((block % threads) * (block.max() + 1) + block) * tile * tile + inside
    return torch.argsort(key.reshape(-1))
