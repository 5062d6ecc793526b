"""Cameras at the extremes: focal lengths of 10 px and 1e5 px, 1x1 and 4000x4000 images (rays
through pixel centres re-project onto those centres, unit directions, finite everywhere), and
scenes at 1e-3 m and 1e4 m that normalization maps to the SAME canonical scene, so training
(which only sees the normalized scene) behaves the same."""

import itertools
import math

import numpy as np
import pytest
import torch

from recon.cameras import Cameras, camera_rays, project_points
from recon.cameras.cameras import intrinsics_matrix, invert_rigid
from recon.cameras.rays import rays_from_pixels
from recon.sfm.normalize import normalize_scene

CASES = list(itertools.product([10.0, 1e5], [1, 4000]))


def K_of(f: float, size: int, dtype) -> torch.Tensor:
    one = torch.ones(1, dtype=dtype)
    return intrinsics_matrix(f * one, f * one, size / 2 * one, size / 2 * one)[0]


def border_pixels(size: int, dtype) -> torch.Tensor:
    """Pixel centres of the corners, edge midpoints and centre of a size x size image."""
    c = sorted({0.5, size / 2 + 0.5 if size > 1 else 0.5, size - 0.5})
    return torch.tensor(list(itertools.product(c, c)), dtype=dtype)


@pytest.mark.parametrize("f, size", CASES)
# float32 in the camera frame: 2e-3 px. A float32 WORLD frame cannot do this at f = 1e5 (a pixel
# spans 1e-5 rad, float32 rounding of a 2 m camera offset moves a point 1 cm away by ~2 px),
# so the posed camera is checked in float64, to 1e-8 px.
@pytest.mark.parametrize(
    "dtype, tol_px, posed", [(torch.float32, 2e-3, False), (torch.float64, 1e-8, True)]
)
def test_rays_reproject_onto_their_pixels(f, size, dtype, tol_px, posed):
    K = K_of(f, size, dtype)
    world_from_cam = torch.eye(4, dtype=dtype)
    if posed:
        world_from_cam[:3, :3] = torch.tensor(
            [[1, 0, 0], [0, math.cos(0.3), -math.sin(0.3)], [0, math.sin(0.3), math.cos(0.3)]],
            dtype=dtype,
        )
        world_from_cam[:3, 3] = torch.tensor([1.0, -2.0, 0.5], dtype=dtype)
    uv = border_pixels(size, dtype)
    o, d, z_per_t = rays_from_pixels(uv, K, world_from_cam)
    assert torch.isfinite(d).all() and torch.isfinite(z_per_t).all() and (z_per_t > 0).all()
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(len(uv), dtype=dtype))
    for depth in (1e-2, 1.0, 1e3):  # points at z-depth `depth` along each ray
        p_world = o + (depth / z_per_t)[:, None] * d
        p_cam = (
            invert_rigid(world_from_cam)
            @ torch.cat([p_world, torch.ones_like(p_world[:, :1])], -1).T
        ).T
        uv_back, z = project_points(p_cam[:, :3], K)
        assert float((uv_back - uv).abs().max()) < tol_px
        torch.testing.assert_close(
            z, torch.full_like(z, depth), rtol=1e-5 if dtype == torch.float32 else 1e-12, atol=0
        )


def test_a_one_pixel_camera_looks_down_its_optical_axis():
    for f in (10.0, 1e5):
        cams = Cameras(
            K_of(f, 1, torch.float32)[None],
            torch.eye(4)[None],
            torch.tensor([1]),
            torch.tensor([1]),
        )
        o, d, z = camera_rays(cams, 0)
        assert o.shape == d.shape == (1, 1, 3) and z.shape == (1, 1)
        assert d[0, 0].tolist() == [0.0, 0.0, 1.0] and float(z[0, 0]) == 1.0


def test_4000_px_camera_scaled_to_one_pixel_keeps_the_centre_ray():
    big = Cameras(
        K_of(1e5, 4000, torch.float64)[None],
        torch.eye(4, dtype=torch.float64)[None],
        torch.tensor([4000]),
        torch.tensor([4000]),
    )
    small = big.scaled(1 / 4000)
    assert small.width.tolist() == [1] and small.height.tolist() == [1]
    _, d, _ = camera_rays(small, 0)
    torch.testing.assert_close(d[0, 0], torch.tensor([0.0, 0, 1], dtype=torch.float64))


def ring_scene(scale: float, offset=(3.0, -7.0, 2.0)):
    """12 cameras on a ring looking at a cloud of points; every length multiplied by `scale`."""
    rng = np.random.default_rng(0)
    target = np.array(offset) * scale
    c2w = []
    for a in np.linspace(0, 2 * np.pi, 12, endpoint=False):
        eye = target + scale * np.array([4 * np.cos(a), 4 * np.sin(a), 1.5])
        fwd = (target - eye) / np.linalg.norm(target - eye)
        right = np.cross(fwd, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(fwd, right), fwd, eye
        c2w.append(m)
    points = target + scale * rng.normal(size=(400, 3))
    K = np.tile(np.array([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]]), (12, 1, 1))
    return np.stack(c2w), K, np.full((12, 2), 64.0), points


@pytest.mark.parametrize("with_points", [True, False])
def test_tiny_and_huge_scenes_normalize_to_the_same_scene(with_points):
    ref = None
    for scale in (1e-3, 1.0, 1e4):
        c2w, K, sizes, points = ring_scene(scale)
        sim, aabb = normalize_scene(c2w, K, sizes, points if with_points else None)
        cams = sim.world_from_cam_to_scene(c2w)
        pts = sim.apply(points)
        assert np.isfinite(cams).all() and np.abs(cams[:, :3, 3]).max() <= 1
        # metric outputs map back: a scene-unit depth of 1 is 1/s_sim metres
        np.testing.assert_allclose(sim.invert_points(pts), points, rtol=1e-9, atol=1e-12 * scale)
        if ref is None:
            ref = (cams, aabb, pts, sim.scale * scale)
            continue
        np.testing.assert_allclose(cams, ref[0], atol=1e-9)
        np.testing.assert_allclose(aabb, ref[1], atol=1e-9)
        np.testing.assert_allclose(pts, ref[2], atol=1e-9)
        assert sim.scale * scale == pytest.approx(ref[3], rel=1e-9)
