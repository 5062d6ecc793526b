"""Plane-sweep stereo: the NCC against a brute-force twin, the sub-plane refinement worked by
hand, and the sweep recovering a textured plane's depth between two synthetic cameras."""

import math

import pytest
import torch
import torch.nn.functional as F

from recon.cameras.rays import pixel_centers, unproject_pixels
from recon.mvs.plane_sweep import (
    best_depth,
    box_mean,
    inverse_depth_planes,
    sweep_scores,
    windowed_ncc,
)


def test_box_mean_matches_average_pooling_at_the_borders_too():
    x = torch.rand(2, 1, 9, 13, dtype=torch.float64)
    for window in (3, 5, 7):
        want = F.avg_pool2d(x, window, 1, window // 2, count_include_pad=False)
        torch.testing.assert_close(box_mean(x, window), want)


def brute_ncc(a, b, v, u, r):
    """NCC of the patches about (v, u), clipped to the image, in float64 loops."""
    rows = range(max(0, v - r), min(a.shape[0], v + r + 1))
    cols = range(max(0, u - r), min(a.shape[1], u + r + 1))
    pa = torch.stack([a[i, j] for i in rows for j in cols]).double()
    pb = torch.stack([b[i, j] for i in rows for j in cols]).double()
    da, db = pa - pa.mean(), pb - pb.mean()
    return float((da * db).mean() / math.sqrt(float((da * da).mean() * (db * db).mean())))


def test_windowed_ncc_matches_a_brute_force_twin():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(10, 12, generator=g, dtype=torch.float64)
    b = 0.5 * a + 0.3 * torch.rand(10, 12, generator=g, dtype=torch.float64)
    got = windowed_ncc(a[None, None], b[None, None], 5)[0, 0]
    for v, u in [(0, 0), (4, 6), (9, 11), (2, 10)]:
        assert float(got[v, u]) == pytest.approx(brute_ncc(a, b, v, u, 2), abs=1e-9)


def test_windowed_ncc_ignores_gain_and_offset_and_flips_sign():
    a = torch.rand(1, 1, 16, 16, dtype=torch.float64)
    torch.testing.assert_close(windowed_ncc(a, 2.0 * a + 0.1, 7), torch.ones_like(a))
    torch.testing.assert_close(windowed_ncc(a, -a, 7), -torch.ones_like(a))
    flat = torch.full_like(a, 0.5)
    assert windowed_ncc(a, flat, 7).abs().max() < 1e-6  # a flat patch scores ~0, not NaN


def test_inverse_depth_planes_are_uniform_in_disparity():
    z = inverse_depth_planes(1.0, 4.0, 4)
    torch.testing.assert_close(1.0 / z, torch.tensor([1.0, 0.75, 0.5, 0.25]))


def test_best_depth_parabola_worked_example():
    planes = inverse_depth_planes(1.0, 3.0, 5)  # 1/z: 1, 5/6, 2/3, 1/2, 1/3
    scores = torch.tensor([0.0, 0.2, 0.8, 0.6, 0.1])[:, None, None]
    depth, score = best_depth(scores, planes)
    # delta = (0.2 - 0.6) / (2 (0.2 - 1.6 + 0.6)) = 0.25: a quarter from plane 2 to plane 3
    inv = 2 / 3 + 0.25 * (1 / 2 - 2 / 3)
    assert float(depth) == pytest.approx(1 / inv, rel=1e-6)
    assert float(score) == pytest.approx(0.8)


def test_best_depth_keeps_an_end_plane_unrefined():
    planes = inverse_depth_planes(1.0, 3.0, 3)
    depth, _ = best_depth(torch.tensor([0.9, 0.5, 0.1])[:, None, None], planes)
    assert float(depth) == pytest.approx(1.0)


def texture(x, y):
    """A smooth, non-repeating grey texture on the plane."""
    return (
        0.5
        + 0.2 * torch.sin(7.1 * x + 1.3 * torch.sin(3.7 * y))
        + 0.15 * torch.cos(5.3 * y - 2.1 * x)
        + 0.1 * torch.sin(11.7 * (x + y))
    )


def plane_image(K, cam_from_world, depth_of_plane, size):
    """The textured plane z = depth_of_plane (world) seen by a camera looking down +z."""
    W, H = size
    uv = pixel_centers(W, H, dtype=torch.float64)
    rays = unproject_pixels(uv, torch.ones(H, W, dtype=torch.float64), K)
    centre = -cam_from_world[:3, 3]  # the rigs below are pure translations
    t = (depth_of_plane - centre[2]) / rays[..., 2]
    hit = centre + t[..., None] * rays
    return texture(hit[..., 0], hit[..., 1]).float()


def test_sweep_recovers_the_depth_of_a_textured_plane():
    W, H, f = 48, 40, 50.0
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]], dtype=torch.float64)
    rigs = [torch.eye(4, dtype=torch.float64) for _ in range(3)]
    rigs[1][0, 3], rigs[2][1, 3] = -0.3, 0.25  # cam_from_world: centres at x = 0.3, y = -0.25
    z_true = 2.0
    images = [plane_image(K, m, z_true, (W, H)) for m in rigs]
    planes = inverse_depth_planes(1.5, 3.0, 48)
    scores = sweep_scores(
        images[0],
        images[1:],
        K.float(),
        [K.float()] * 2,
        [(m @ torch.linalg.inv(rigs[0])).float() for m in rigs[1:]],
        planes,
        window=7,
        top_k=2,
    )
    depth, score = best_depth(scores, planes)
    inner = depth[8:-8, 8:-8]  # away from where the sources leave the image
    spacing = z_true**2 * (1 / 1.5 - 1 / 3) / 47  # plane spacing in depth at z_true: 0.028
    assert float((inner - z_true).abs().median()) < 0.25 * spacing  # refined below a plane
    assert float(score[8:-8, 8:-8].median()) > 0.9
