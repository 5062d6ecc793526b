"""Samplers: ray/box intersection, stratified intervals, inverse-CDF resampling."""

import torch

from recon.volrend import (
    intervals_from_points,
    merge_points,
    ray_aabb_intersect,
    sample_pdf,
    spaced_intervals,
    stratified_intervals,
)

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def test_ray_aabb_hit_miss_inside_and_axis_parallel():
    o = torch.tensor(
        [
            [-3.0, 0.0, 0.0],
            [-3.0, 2.0, 0.0],
            [0.0, 0.0, 0.0],
            [0.5, 0.5, -5.0],
            [3.0, 0.0, 0.0],
            [-3.0, -3.0, -3.0],
        ]
    )
    d = torch.tensor(
        [
            [1.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [1.0, 0.0, 0.0],
            [1.0, 1.0, 1.0],
        ]
    )
    d = d / d.norm(dim=-1, keepdim=True)
    t0, t1, hit = ray_aabb_intersect(o, d, AABB)
    assert hit.tolist() == [True, False, True, True, False, True]
    torch.testing.assert_close(t0[[0, 2, 3]], torch.tensor([2.0, 0.0, 4.0]))  # inside starts at 0
    torch.testing.assert_close(t1[[0, 2, 3]], torch.tensor([4.0, 1.0, 6.0]))
    s3 = 3**0.5
    torch.testing.assert_close(t0[5], torch.tensor(2 * s3)) and torch.testing.assert_close(
        t1[5], torch.tensor(4 * s3)
    )
    assert t0[1] == 0 and t1[1] == 0 and t0[4] == 0 and t1[4] == 0  # misses: empty range


def test_ray_aabb_brute_force_twin():
    g = torch.Generator().manual_seed(0)
    o = torch.randn(500, 3, generator=g) * 2
    d = torch.nn.functional.normalize(torch.randn(500, 3, generator=g), dim=-1)
    t0, t1, hit = ray_aabb_intersect(o, d, AABB)
    ts = torch.linspace(0, 8, 8001)
    pts = o[:, None] + ts[None, :, None] * d[:, None]
    inside = (pts.abs() <= 1).all(-1)
    brute_hit = inside.any(-1)
    assert (brute_hit & ~hit).sum() == 0 and (hit & ~brute_hit).sum() <= 2  # grazing rays
    first = torch.where(inside, ts, torch.inf).amin(-1)
    last = torch.where(inside, ts, -torch.inf).amax(-1)
    both = hit & brute_hit
    assert ((first - t0)[both].abs() < 2e-3).all() and ((last - t1)[both].abs() < 2e-3).all()


def test_stratified_tiles_range_and_jitter_stays_in_strata():
    near, far = torch.tensor([1.0, 2.0]), torch.tensor([3.0, 6.0])
    t0, t1 = stratified_intervals(near, far, 8, jitter=False)
    torch.testing.assert_close(t1 - t0, ((far - near) / 8)[:, None].expand(2, 8))
    g = torch.Generator().manual_seed(0)
    j0, j1 = stratified_intervals(near, far, 8, jitter=True, generator=g)
    assert (j0[:, 0] == near).all() and (j1[:, -1] == far).all()
    torch.testing.assert_close(j0[:, 1:], j1[:, :-1])  # contiguous
    assert ((j1 - j0) > 0).all()
    # each interior edge lies between the centres of its neighbouring bins
    centres = 0.5 * (t0 + t1)
    assert ((j1[:, :-1] >= centres[:, :-1]) & (j1[:, :-1] <= centres[:, 1:])).all()


def test_jittered_midpoints_cover_range_uniformly():
    g = torch.Generator().manual_seed(1)
    n = 20000
    t0, t1 = stratified_intervals(torch.zeros(n), torch.ones(n), 4, jitter=True, generator=g)
    mids = 0.5 * (t0 + t1)
    assert t0.min() == 0 and t1.max() == 1
    # the midpoints of each stratum spread over their bin (not stuck at the centre)
    assert (mids[:, 1].max() - mids[:, 1].min()) > 0.2


def test_disparity_spacing_endpoints():
    near, far = torch.tensor([0.5]), torch.tensor([100.0])
    inv = lambda t: 1.0 / t
    t0, t1 = spaced_intervals(near, far, 16, False, inv, inv)
    torch.testing.assert_close(t0[:, 0], near) and torch.testing.assert_close(t1[:, -1], far)
    assert ((t1 - t0) > 0).all() and (t1 - t0)[0, -1] > 10 * (t1 - t0)[0, 0]


def test_sample_pdf_matches_monte_carlo_histogram():
    edges = torch.tensor([[0.0, 1.0, 2.0, 4.0, 5.0]])
    weights = torch.tensor([[1.0, 0.0, 3.0, 4.0]])
    g = torch.Generator().manual_seed(0)
    n = 200000
    t = sample_pdf(edges, weights, n, jitter=True, generator=g, eps=0.0)
    assert (t[:, 1:] >= t[:, :-1]).all()
    hist = torch.histc(t[0], bins=5, min=0.0, max=5.0) / n
    # pdf piecewise constant: mass 1/8 on [0,1], 0 on [1,2], 3/8 on [2,4] (3/16 per unit), 1/2 on [4,5]
    expected = torch.tensor([1 / 8, 0.0, 3 / 16, 3 / 16, 1 / 2])
    torch.testing.assert_close(hist, expected, atol=4e-3, rtol=0)
    # deterministic variant hits the same quantiles
    td = sample_pdf(edges, weights, 8, jitter=False, eps=0.0)
    u = (torch.arange(8) + 0.5) / 8
    cdf = torch.tensor([0.0, 1 / 8, 1 / 8, 1 / 2, 1.0])
    for ui, ti in zip(u, td[0]):
        i = int(torch.searchsorted(cdf, ui, right=True)) - 1
        expect = edges[0, i] + (ui - cdf[i]) / (cdf[i + 1] - cdf[i]) * (
            edges[0, i + 1] - edges[0, i]
        )
        assert abs(ti - expect) < 1e-6


def test_sample_pdf_zero_weights_is_uniform_and_no_grad():
    edges = torch.linspace(0, 1, 5)[None].repeat(2, 1)
    weights = torch.zeros(2, 4, requires_grad=True)
    t = sample_pdf(edges, weights, 4, jitter=False)
    torch.testing.assert_close(
        t, torch.tensor([0.125, 0.375, 0.625, 0.875]).expand(2, 4), atol=1e-4, rtol=0
    )
    assert not t.requires_grad


def test_intervals_from_points_and_merge():
    t = merge_points(torch.tensor([[1.0, 3.0]]), torch.tensor([[2.0, 0.5]]))
    assert t.tolist() == [[0.5, 1.0, 2.0, 3.0]]
    s, e = intervals_from_points(t, torch.tensor([0.0]), torch.tensor([4.0]))
    assert s.tolist() == [[0.0, 0.75, 1.5, 2.5]] and e.tolist() == [[0.75, 1.5, 2.5, 4.0]]
