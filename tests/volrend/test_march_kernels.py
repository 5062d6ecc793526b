import math

import pytest
import torch

from recon.volrend import OccupancyGrid, ray_aabb_intersect, scene_to_unit_cube
from recon.volrend.march_kernels import (
    cell_exit,
    last_in_cell,
    march_interval,
    march_occupied,
    tile_order,
    warp,
)


@pytest.mark.parametrize(
    "unbounded,cone,disparity_from",
    [(False, 0.0, math.inf), (True, 1 / 64, math.inf), (True, 1 / 64, 3.0)],
)
def test_numba_march_matches_occupancy_grid_sample(unbounded, cone, disparity_from):
    g = torch.Generator().manual_seed(0)
    res = 16
    grid = OccupancyGrid(res)
    grid.occupied.copy_(torch.rand(res**3, generator=g) > 0.6)
    aabb = torch.tensor([[-0.5, -0.4, -0.3], [0.5, 0.6, 0.4]])
    R = 300
    origins = torch.randn(R, 3, generator=g) * 1.5
    dirs = torch.nn.functional.normalize(-origins + 0.3 * torch.randn(R, 3, generator=g), dim=-1)
    if unbounded:
        t_min, t_max = torch.full((R,), 0.05), torch.full((R,), 50.0)
    else:
        t_min, t_max, _ = ray_aabb_intersect(origins, dirs, aabb)
    u = torch.rand(R, generator=g)
    step = 0.02

    def to_unit(x):
        return scene_to_unit_cube(x, aabb, unbounded)

    ref = grid.march_torch(
        origins, dirs, t_min, t_max, to_unit, step, cone, u, disparity_from=disparity_from
    )
    fast = march_occupied(
        origins,
        dirs,
        t_min,
        t_max,
        grid.occupied,
        res,
        aabb,
        unbounded,
        step,
        cone,
        u,
        disparity_from=disparity_from,
    )
    assert ref[0].numel() > 100
    # the midpoint of an interval on a cell boundary may round either way in float32
    assert abs(ref[0].numel() - fast[0].numel()) <= 0.002 * ref[0].numel() + 2
    if ref[0].numel() == fast[0].numel():
        assert torch.equal(ref[0], fast[0])
        assert torch.allclose(ref[1], fast[1], atol=1e-5) and torch.allclose(
            ref[2], fast[2], atol=1e-5
        )


@pytest.mark.parametrize("unbounded,cone", [(False, 0.0), (True, 1 / 64)])
def test_numba_march_cap_matches_the_torch_twin_and_keeps_the_first_samples(unbounded, cone):
    g = torch.Generator().manual_seed(1)
    res, cap = 16, 7
    grid = OccupancyGrid(res)
    grid.occupied.copy_(torch.rand(res**3, generator=g) > 0.3)
    aabb = torch.tensor([[-0.5, -0.4, -0.3], [0.5, 0.6, 0.4]])
    R = 200
    origins = torch.randn(R, 3, generator=g, dtype=torch.float64) * 1.5
    dirs = torch.nn.functional.normalize(
        -origins + 0.3 * torch.randn(R, 3, generator=g, dtype=torch.float64), dim=-1
    )
    if unbounded:
        t_min, t_max = (
            torch.full((R,), 0.05, dtype=torch.float64),
            torch.full((R,), 50.0, dtype=torch.float64),
        )
    else:
        t_min, t_max, _ = ray_aabb_intersect(origins, dirs, aabb.double())
    u = torch.rand(R, generator=g, dtype=torch.float64)
    step = 0.02

    def to_unit(x):
        return scene_to_unit_cube(x, aabb.double(), unbounded)

    full = grid.march_torch(origins, dirs, t_min, t_max, to_unit, step, cone, u)
    ref = grid.march_torch(origins, dirs, t_min, t_max, to_unit, step, cone, u, max_samples=cap)
    fast = march_occupied(
        origins,
        dirs,
        t_min,
        t_max,
        grid.occupied,
        res,
        aabb,
        unbounded,
        step,
        cone,
        u,
        max_samples=cap,
    )
    counts = torch.bincount(fast[0], minlength=R)
    full_counts = torch.bincount(full[0], minlength=R)
    assert counts.max() == cap and (full_counts > cap).sum() > 20  # the cap binds on many rays
    assert torch.equal(counts, full_counts.clamp(max=cap))
    # in float64 the twins agree exactly, and the kept samples are each ray's first ones
    assert (
        torch.equal(ref[0], fast[0])
        and torch.equal(ref[1], fast[1])
        and torch.equal(ref[2], fast[2])
    )
    first = torch.cumsum(full_counts, 0) - full_counts
    rank = torch.arange(full[0].numel()) - first[full[0]]
    kept = rank < cap
    assert torch.equal(full[1][kept], fast[1]) and torch.equal(full[2][kept], fast[2])


def test_cell_exit_worked_example():
    """A ray from unit-cube point (0.1, 0.5, 0.9) along (0.5, -0.25, 0) (per unit t), 4 cells
    an axis: it is in cell (0, 2, 3); it leaves x's cell at x = 0.25 (t = 0.3) before y's at
    y = 0.5 (t = 0; it starts on that face, running down: cell 2 spans [0.5, 0.75), so the
    face ahead is 0.5, t = 0) -> 0. From (0.1, 0.6, 0.9): y's face 0.5 at t = 0.4, x's at 0.3."""
    assert cell_exit((0.1, 0.5, 0.9, 0.5, -0.25, 0.0), 0.1, 0.5, 0.9, 4) == pytest.approx(0.0)
    assert cell_exit((0.1, 0.6, 0.9, 0.5, -0.25, 0.0), 0.1, 0.6, 0.9, 4) == pytest.approx(0.3)
    # x = 1 counts as the last cell; running along -z the ray leaves through z = 0.75
    assert cell_exit((1.0, 0.6, 0.9, 0.0, 0.0, -1.0), 1.0, 0.6, 0.9, 4) == pytest.approx(0.15)


@pytest.mark.parametrize("cone", [0.0, 1 / 16])
def test_last_in_cell_skips_only_intervals_inside_the_cell(cone):
    """Brute force: every interval k' in (k, last] has its midpoint in interval k's cell, and
    interval last + 1 ends past the cell (last is the largest such index), with jitter u."""
    g = torch.Generator().manual_seed(1)
    n, step, t_far = 8, 0.013, math.inf
    checked = 0
    for _ in range(200):
        a = torch.rand(3, generator=g).double().tolist()
        b = torch.nn.functional.normalize(torch.randn(3, generator=g).double(), dim=0).tolist()
        u, t_min = float(torch.rand(1, generator=g)), 0.02
        s_min = warp(t_min, step, cone, t_far)
        k = int(torch.randint(1, 40, (1,), generator=g))
        mid = 0.5 * sum(march_interval(k, t_min, math.inf, s_min, u, step, cone, t_far))
        x = [a[i] + mid * b[i] for i in range(3)]
        if not all(0.0 <= v < 1.0 for v in x):
            continue
        cell = [int(v * n) for v in x]
        t_exit = cell_exit((*a, *b), *x, n)
        last = last_in_cell(k, t_exit, s_min, u, step, cone, t_far)
        for kk in range(k + 1, last + 1):
            m = 0.5 * sum(march_interval(kk, t_min, math.inf, s_min, u, step, cone, t_far))
            assert [int((a[i] + m * b[i]) * n) for i in range(3)] == cell
        if last > k:
            assert (
                march_interval(last + 1, t_min, math.inf, s_min, u, step, cone, t_far)[1] > t_exit
            )
            checked += 1
    assert checked > 50


def test_tile_order_deals_whole_tiles_to_every_thread():
    """A permutation of the pixels; each thread's run (one of `threads` equal runs, numba's
    static schedule) holds whole 8 x 8 tiles from the top and the bottom of the image."""
    H, W, threads = 40, 48, 2
    order = tile_order(H, W, threads)
    assert torch.equal(order.sort().values, torch.arange(H * W))
    for run in order.view(threads, -1):
        y, x = run // W, run % W
        tiles = (y // 8) * (W // 8) + x // 8
        assert (torch.bincount(tiles, minlength=30)[tiles.unique()] == 64).all()
        assert y.min() < 8 and y.max() >= H - 8
        assert (tiles[::64].repeat_interleave(64) == tiles).all()  # one tile at a time
