"""Occupancy-grid marching: same image as dense sampling with far fewer samples."""

import math

import pytest
import torch

from recon.volrend import (
    OccupancyGrid,
    march_intervals,
    ray_aabb_intersect,
    scene_to_unit_cube,
    stratified_intervals,
    terminated_mask,
    volume_render,
)
from recon.volrend.occupancy import (
    _unwarp,
    _warp,
    cell_points,
    cells_of,
    dilated_cells,
    first_per_ray,
    march_terminated,
    ray_spans,
)

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
CENTRE, RADIUS, SIGMA = torch.tensor([0.2, -0.1, 0.0]), 0.4, 30.0


def sphere_density(x):
    return SIGMA * ((x - CENTRE).norm(dim=-1) < RADIUS).float()


def cube_density(x):
    # faces on cell boundaries of a 32^3 grid over [-1, 1]^3 (cell 1/16): every cell is either
    # fully empty or fully dense, so skipping must reproduce dense marching exactly
    return SIGMA * ((x - 0.125).abs() < 0.25).all(dim=-1).float()


def sphere_colour(x):
    return ((x - CENTRE) / RADIUS * 0.5 + 0.5).clamp(0, 1)


def rays(n=400, seed=0):
    g = torch.Generator().manual_seed(seed)
    target = (torch.rand(n, 3, generator=g) - 0.5) * 1.2
    o = torch.tensor([0.0, 0.0, -3.0]).expand(n, 3)
    d = torch.nn.functional.normalize(target - o, dim=-1)
    return o, d


def test_march_intervals_tile_the_range():
    t_min, t_max = torch.tensor([0.0, 1.0, 2.0]), torch.tensor([1.0, 1.0, 2.32])
    ri, s, e = march_intervals(t_min, t_max, 0.1, u=torch.tensor([0.0, 0.5, 0.5]))
    assert (ri == 0).sum() == 10 and (ri == 1).sum() == 0 and (ri == 2).sum() == 4
    for r in (0, 2):
        m = ri == r
        assert s[m][0] == t_min[r] and e[m][-1] == t_max[r]
        torch.testing.assert_close(s[m][1:], e[m][:-1])
    torch.testing.assert_close(e[ri == 2] - s[ri == 2], torch.tensor([0.05, 0.1, 0.1, 0.07]))


def test_cone_warp_inverts_and_steps_grow():
    t = torch.logspace(-3, 3, 50, dtype=torch.float64)
    torch.testing.assert_close(_unwarp(_warp(t, 0.01, 1 / 64), 0.01, 1 / 64), t)
    _, s, e = march_intervals(torch.tensor([0.05]), torch.tensor([100.0]), 0.01, 1 / 64)
    d = e - s
    assert d[1:-1].min() >= 0.01 - 1e-6 and d[-2] > 1.0 and e[-1] == 100.0
    torch.testing.assert_close(s[1:], e[:-1])


def test_disparity_warp_inverts_is_smooth_and_reaches_infinity_in_one_over_c_steps():
    step, c, t_d = 0.01, 1 / 64, 2.0  # linear to t_sw = 0.64, log to 2, then linear in 1/t
    t = torch.logspace(-3, 6, 200, dtype=torch.float64)
    torch.testing.assert_close(_unwarp(_warp(t, step, c, t_d), step, c, t_d), t)
    # ds/dt is continuous: 1/step below t_sw, 1/(c t) between, t_d/(c t^2) beyond
    for knot in (step / c, t_d):
        h = 1e-7
        lo, hi = (
            torch.tensor([knot - h, knot], dtype=torch.float64),
            torch.tensor([knot, knot + h], dtype=torch.float64),
        )
        slopes = (_warp(hi, step, c, t_d) - _warp(lo, step, c, t_d)) / h
        torch.testing.assert_close(slopes[0], slopes[1], rtol=1e-5, atol=0)
    s_d = _warp(torch.tensor([t_d], dtype=torch.float64), step, c, t_d)
    s_inf = _warp(torch.tensor([1e300], dtype=torch.float64), step, c, t_d)
    torch.testing.assert_close(s_inf - s_d, torch.tensor([1 / c], dtype=torch.float64))
    assert _unwarp(s_inf + 0.5, step, c, t_d).isinf().all()  # past s(inf): infinitely far
    # a ray to t = 1e4: 64 linear + 64 ln(2 / 0.64) log + < 64 disparity intervals, instead of
    # the 64 ln(1e4 / 0.64) ~ 618 log intervals of the cone alone
    _, s, e = march_intervals(torch.tensor([0.0]), torch.tensor([1e4]), step, c, disparity_from=t_d)
    assert len(s) == math.ceil(64 + 64 * math.log(2 / 0.64) + 64 * (1 - 2 / 1e4))
    assert s[0] == 0 and e[-1] == 1e4 and torch.equal(s[1:], e[:-1])
    _, s_cone, _ = march_intervals(torch.tensor([0.0]), torch.tensor([1e4]), step, c)
    assert len(s_cone) == math.ceil(64 + 64 * math.log(1e4 / 0.64))
    # the same up to t_d
    n_d = int(s_d.item())
    torch.testing.assert_close(s[:n_d], s_cone[:n_d])


def test_cells_round_trip():
    idx = torch.arange(4**3)
    x = cell_points(idx, 4, torch.full((64, 3), 0.5))
    back, inside = cells_of(x, 4)
    assert (back == idx).all() and inside.all()
    _, inside = cells_of(torch.tensor([[1.2, 0.5, 0.5], [1.0, 1.0, 0.0]]), 4)
    assert inside.tolist() == [False, True]


def trained_grid(density):
    grid = OccupancyGrid(32)
    g = torch.Generator().manual_seed(0)
    step = 2 * math.sqrt(3) / 256
    grid.update(lambda u: density(u * 2 - 1), step, warmup=True, generator=g)
    assert grid.occupied.all()  # warm-up keeps everything occupied
    for _ in range(6):
        grid.update(lambda u: density(u * 2 - 1), step, warmup=False, fraction=1.0, generator=g)
    return grid, step


def test_grid_marks_the_sphere():
    grid, _ = trained_grid(sphere_density)
    frac = grid.occupancy_fraction()
    sphere_frac = 4 / 3 * math.pi * RADIUS**3 / 8
    assert sphere_frac < frac < 4 * sphere_frac
    inside = scene_to_unit_cube(CENTRE[None], AABB, False)
    assert (
        grid.is_occupied(inside).item()
        and not grid.is_occupied(torch.tensor([[0.02, 0.02, 0.02]])).item()
    )


def test_skipping_renders_like_dense_sampling():
    grid, step = trained_grid(cube_density)
    o, d = rays()
    R = o.shape[0]
    t_min, t_max, _ = ray_aabb_intersect(o, d, AABB)
    bg = torch.tensor([1.0, 1.0, 1.0])
    # dense reference: every marching step, no skipping, no termination
    dri, t0, t1 = march_intervals(t_min, t_max, step)
    x = o[dri] + (0.5 * (t0 + t1))[:, None] * d[dri]
    dense = volume_render(cube_density(x), sphere_colour(x), t0, t1, dri, R, background=bg)
    to_unit = lambda p: scene_to_unit_cube(p, AABB, False)
    ri, s, e = grid.march_torch(o, d, t_min, t_max, to_unit, step)
    xm = o[ri] + (0.5 * (s + e))[:, None] * d[ri]
    sig = cube_density(xm)
    keep = terminated_mask(sig, s, e, ri, eps=1e-4)
    ri, s, e, xm, sig = ri[keep], s[keep], e[keep], xm[keep], sig[keep]
    sparse = volume_render(sig, sphere_colour(xm), s, e, ri, R, background=bg)
    assert (sparse.rgb - dense.rgb).abs().max() < 2e-4  # early termination at T < 1e-4 only
    assert (sparse.acc - dense.acc).abs().max() < 2e-4
    assert (dense.acc > 0.5).sum() > 50  # the rays do see the object
    assert s.shape[0] < 0.2 * t0.shape[0]
    # and the dense marching itself converges to a fine stratified quadrature
    f0, f1 = stratified_intervals(t_min, t_max, 4096, jitter=False)
    xf = o[:, None] + 0.5 * (f0 + f1)[..., None] * d[:, None]
    fine = volume_render(cube_density(xf), sphere_colour(xf), f0, f1, background=bg)
    assert (fine.rgb - dense.rgb).abs().mean() < 3e-3


def test_terminated_mask_drops_after_opaque():
    sig = torch.tensor([0.0, 100.0, 1.0, 1.0, 1.0, 1.0])
    t = torch.arange(6.0)
    ri = torch.tensor([0, 0, 0, 1, 1, 1])
    assert terminated_mask(sig, t, t + 1, ri).tolist() == [True, True, False, True, True, True]


def _march_with_termination_twin(density, first, max_samples):
    """march_terminated against its literal twin: march everything, terminated_mask over it."""
    grid, step = trained_grid(density)
    o, d = rays(n=300)
    t_min, t_max, _ = ray_aabb_intersect(o, d, AABB)
    u = torch.rand(o.shape[0], generator=torch.Generator().manual_seed(2))
    sigma = lambda x: density(x * 2 - 1)

    def march(ids, k):
        ri, t0, t1 = grid.march(
            o[ids], d[ids], t_min[ids], t_max[ids], AABB, False, step, 0.0, u[ids], k
        )  # fmt: skip
        x = scene_to_unit_cube(o[ids][ri] + (0.5 * (t0 + t1))[:, None] * d[ids][ri], AABB, False)
        return ri, t0, t1, x

    ids = torch.arange(o.shape[0])
    ri, t0, t1, x = march(ids, max_samples)
    keep = terminated_mask(sigma(x), t0, t1, ri, 1e-4)
    got = march_terminated(march, sigma, o.shape[0], 1e-4, first, max_samples)
    for a, b in zip(got[:4], (ri[keep], t0[keep], t1[keep], x[keep])):
        assert torch.equal(a, b)
    # a density closure with features: the same samples, with their sigmas and features
    both = march_terminated(
        march, lambda x: (sigma(x), 3 * x), o.shape[0], 1e-4, first, max_samples
    )  # fmt: skip
    for a, b in zip(both, (*got[:4], sigma(x[keep]), 3 * x[keep], got[4])):
        assert torch.equal(torch.as_tensor(a), torch.as_tensor(b))
    return got[4], ri.shape[0], int(keep.sum())


def test_march_terminated_keeps_what_terminated_mask_keeps_and_evaluates_less():
    # a dense sphere: rays through it terminate a few samples in, the later rounds are short
    for first in (2, 4):
        evaluated, marched, kept = _march_with_termination_twin(sphere_density, first, 0)
        assert kept < marched and evaluated < 0.8 * marched, (first, evaluated, marched)
    # a thin density that never terminates: every ray open after the first round
    faint = lambda x: 0.01 * sphere_density(x)
    evaluated, marched, kept = _march_with_termination_twin(faint, 4, 0)
    assert evaluated == marched == kept
    # with a cap on samples per ray, and a first round at and beyond it
    for first in (1, 3, 6, 0):
        _march_with_termination_twin(sphere_density, first, 6)


def test_ray_spans_worked_example_and_empty_rays():
    ri = torch.tensor([0, 0, 2])
    lo, hi = ray_spans(ri, torch.tensor([1.0, 3.0, 5.0]), torch.tensor([2.0, 4.0, 6.0]), 3)
    assert lo.tolist() == [1.0, 0.0, 5.0] and hi.tolist() == [4.0, 0.0, 6.0]
    lo, hi = ray_spans(ri, torch.tensor([1.0, 3.0, 0.2]), torch.tensor([2.0, 4.0, 6.0]), 3, pad=0.5)
    assert lo.tolist() == [0.5, 0.0, 0.0] and hi.tolist() == [4.5, 0.0, 6.5]  # clamped at t = 0


def test_march_dispatch_equals_sample_and_spans_hold_every_occupied_sample():
    grid, step = trained_grid(sphere_density)
    o, d = rays()
    t_min, t_max, _ = ray_aabb_intersect(o, d, AABB)
    u = torch.rand(o.shape[0], generator=torch.Generator().manual_seed(1))
    ref = grid.march_torch(
        o, d, t_min, t_max, lambda p: scene_to_unit_cube(p, AABB, False), step, 0.0, u
    )
    ri, s, e = grid.march(o, d, t_min, t_max, AABB, False, step, 0.0, u)
    assert torch.equal(ri, ref[0]) and torch.allclose(s, ref[1]) and torch.allclose(e, ref[2])
    lo, hi = ray_spans(ri, s, e, o.shape[0])
    assert (lo[ri] <= s).all() and (e <= hi[ri]).all()
    missed = torch.ones(o.shape[0], dtype=torch.bool)
    missed[ri] = False
    assert missed.any() and (lo[missed] == 0).all() and (hi[missed] == 0).all()


@pytest.mark.parametrize(
    "unbounded,cone,cap", [(False, 0.0, 0), (False, 0.0, 5), (True, 1 / 64, 7)]
)
def test_torch_march_in_rounds_gives_the_samples_of_one_march(unbounded, cone, cap):
    """`march_torch` in many rounds of a few intervals a ray (a tiny per-round budget) against
    its literal definition: every interval at once, the occupied midpoints, the first cap."""
    grid, step = trained_grid(sphere_density)
    o, d = rays(n=200)
    if unbounded:
        t_min, t_max = torch.full((200,), 0.1), torch.full((200,), 30.0)
    else:
        t_min, t_max, _ = ray_aabb_intersect(o, d, AABB)
    u = torch.rand(200, generator=torch.Generator().manual_seed(3))
    to_unit = lambda p: scene_to_unit_cube(p, AABB, unbounded)
    ri, s, e = march_intervals(t_min, t_max, step, cone, u)
    keep = grid.is_occupied(to_unit(o[ri] + (0.5 * (s + e))[:, None] * d[ri]))
    ri, s, e = ri[keep], s[keep], e[keep]
    keep = first_per_ray(ri, cap)
    ref = ri[keep], s[keep], e[keep]
    assert ref[0].numel() > 300
    for budget in (1 << 22, 37, 1):  # one round; many; one interval a ray a round
        got = grid.march_torch(
            o, d, t_min, t_max, to_unit, step, cone, u, cap, round_intervals=budget
        )
        for a, b in zip(got, ref):
            assert torch.equal(a, b), budget


def test_first_per_ray_worked_example():
    ri = torch.tensor([0, 0, 0, 2, 2, 3])
    assert first_per_ray(ri, 2).tolist() == [True, True, False, True, True, True]
    assert first_per_ray(ri, 0).all() and first_per_ray(ri, 1).tolist() == [
        True,
        False,
        False,
        True,
        False,
        True,
    ]


def test_dilated_cells_worked_example_and_edges():
    centre = cell_points(
        torch.tensor([1 + 4 * (1 + 4 * 1)]), 4, torch.full((1, 3), 0.5)
    )  # cell (1, 1, 1)
    mask = dilated_cells(centre, 4, 1)
    ijk = torch.stack(torch.meshgrid(*[torch.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3)
    flat = ijk[:, 0] + 4 * (ijk[:, 1] + 4 * ijk[:, 2])
    expected = torch.zeros(64, dtype=torch.bool)
    expected[flat[(ijk <= 2).all(-1)]] = True
    assert torch.equal(mask, expected) and mask.sum() == 27
    assert torch.equal(dilated_cells(centre, 4, 0).nonzero()[:, 0], torch.tensor([21]))
    # a corner cell's dilation is cut by the grid, points outside the cube mark nothing
    corner = dilated_cells(torch.tensor([[0.99, 0.99, 0.99], [1.5, 0.5, 0.5]]), 4, 1)
    assert corner.sum() == 8 and corner[63]


def test_seeded_grid_keeps_its_seed_through_warm_up_then_follows_the_density():
    grid = OccupancyGrid(32)
    centre_unit = scene_to_unit_cube(CENTRE[None], AABB, False)
    grid.seed(centre_unit, 1)
    assert grid.occupied.sum() == 27 and grid.is_occupied(centre_unit).item()
    g = torch.Generator().manual_seed(0)
    step = 2 * math.sqrt(3) / 256
    grid.update(lambda u: sphere_density(u * 2 - 1), step, warmup=True, generator=g)
    assert grid.occupied.sum() == 27  # warm-up evaluates every cell but keeps the seed
    for _ in range(4):
        grid.update(
            lambda u: sphere_density(u * 2 - 1), step, warmup=False, fraction=1.0, generator=g
        )
    sphere_frac = 4 / 3 * math.pi * RADIUS**3 / 8
    assert (
        sphere_frac < grid.occupancy_fraction() < 4 * sphere_frac
    )  # the whole sphere, not the seed


def test_coarse_level_is_the_any_pool_and_follows_every_write():
    g = torch.Generator().manual_seed(0)
    grid = OccupancyGrid(8)
    grid.occupied.copy_(torch.rand(8**3, generator=g) > 0.97)
    coarse, res = grid.coarse(4)
    assert res == 2
    cells = grid.occupied.view(8, 8, 8).nonzero()  # (k, j, i)
    expected = torch.zeros(2, 2, 2, dtype=torch.bool)
    expected[cells[:, 0] // 4, cells[:, 1] // 4, cells[:, 2] // 4] = True
    assert torch.equal(coarse.view(2, 2, 2), expected) and not expected.all()
    assert grid.coarse(4)[0] is coarse  # kept while the bitfield is unchanged
    grid.occupied.fill_(True)  # written in place
    assert grid.coarse(4)[0].all() and grid.occupied_box().tolist() == [[0, 0, 0], [1, 1, 1]]
    grid.load_state_dict({"opacity": grid.opacity, "occupied": torch.zeros(8**3, dtype=torch.bool)})
    assert not grid.coarse(4)[0].any() and grid.occupied_box() is None
    with pytest.raises(ValueError, match="divide"):
        grid.coarse(3)
