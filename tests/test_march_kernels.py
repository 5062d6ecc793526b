import math

import pytest
import torch

from recon.volrend import OccupancyGrid, ray_aabb_intersect, scene_to_unit_cube
from recon.volrend.march_kernels import march_occupied


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
