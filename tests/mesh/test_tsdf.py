import numpy as np
import pytest
import torch

from recon.cameras import Cameras, camera_rays
from recon.cameras.cameras import intrinsics_matrix
from recon.cameras.look_at import look_at
from recon.mesh.marching_cubes import grid_slabs
from recon.mesh.tsdf import (
    TSDFConfig,
    fuse_depth_maps,
    integrate,
    project_tsdf,
    sample_colors,
    tsdf_mesh,
    tsdf_volume,
)

CENTER = torch.tensor([0.1, -0.05, 0.08], dtype=torch.float64)
RADIUS = 0.5
AABB = np.array([[-0.8, -0.8, -0.8], [0.9, 0.8, 0.85]])


def _cube_corner_cameras(size: int = 96, distance: float = 2.2) -> Cameras:
    corners = torch.tensor(
        [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=torch.float64
    )
    eyes = CENTER + distance * corners / corners.norm(dim=1, keepdim=True)
    f = torch.full((8,), size * 1.1, dtype=torch.float64)
    c = torch.full((8,), size / 2, dtype=torch.float64)
    n = torch.full((8,), size, dtype=torch.int64)
    return Cameras(
        intrinsics_matrix(f, f, c, c),
        torch.stack([look_at(e, CENTER, torch.tensor([0.0, 0.0, 1.0])) for e in eyes]),
        n,
        n,
    )


def _render_sphere(cameras: Cameras, background: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Analytic z-depth (C, H, W) by ray-sphere intersection, colour = (p - c) / 2r + 0.5."""
    depths, rgbs = [], []
    for i in range(len(cameras)):
        o, d, z_per_t = camera_rays(cameras, i)
        oc = o - CENTER
        b = (d * oc).sum(-1)
        disc = b**2 - ((oc * oc).sum(-1) - RADIUS**2)
        hit = disc > 0
        t = -b - disc.clamp_min(0).sqrt()
        depths.append(torch.where(hit, t * z_per_t, torch.full_like(t, background)))
        p = o + t[..., None] * d
        rgbs.append(torch.where(hit[..., None], (p - CENTER) / (2 * RADIUS) + 0.5, 0.0))
    return torch.stack(depths), torch.stack(rgbs)


def _project_tsdf_reference(points, cameras, depths, rgbs, trunc):
    """One view at a time with explicit pinhole arithmetic: the twin of `project_tsdf`."""
    n = len(points)
    s_t, s_w, s_v = (torch.zeros(n, dtype=points.dtype) for _ in range(3))
    s_c = torch.zeros(n, 3, dtype=points.dtype)
    for c in range(len(cameras)):
        X = points @ cameras.cam_from_world[c, :3, :3].T + cameras.cam_from_world[c, :3, 3]
        K = cameras.K[c]
        u = K[0, 0] * X[:, 0] / X[:, 2] + K[0, 1] * X[:, 1] / X[:, 2] + K[0, 2]
        v = K[1, 1] * X[:, 1] / X[:, 2] + K[1, 2]
        w_img, h_img = int(cameras.width[c]), int(cameras.height[c])
        for idx in range(n):
            if not (X[idx, 2] > 0 and 0 <= u[idx] < w_img and 0 <= v[idx] < h_img):
                continue
            D = depths[c, int(v[idx]), int(u[idx])]
            sdf = D - X[idx, 2]
            if not (torch.isfinite(D) and D > 0 and sdf >= -trunc):
                continue
            s_t[idx] += min(1.0, sdf / trunc)
            s_w[idx] += 1
            if abs(sdf) < trunc:
                s_c[idx] += rgbs[c, int(v[idx]), int(u[idx])]
                s_v[idx] += 1
    return s_t, s_w, s_c, s_v


def test_project_tsdf_matches_slow_twin():
    cameras = _cube_corner_cameras(size=24)
    depths, rgbs = _render_sphere(cameras, background=0.0)
    depths[0, 3, 5] = float("nan")
    depths[1, 7, 7] = float("inf")
    g = torch.Generator().manual_seed(0)
    points = CENTER + 0.7 * (2 * torch.rand(400, 3, generator=g, dtype=torch.float64) - 1)
    points = torch.cat([points, cameras.centers])  # z = 0, u = v = NaN: must not count
    fast = project_tsdf(points, cameras, depths, rgbs, truncation=0.1)
    slow = _project_tsdf_reference(points, cameras, depths, rgbs, 0.1)
    for a, b in zip(fast, slow):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    assert slow[1].sum() > 100 and slow[3].sum() > 10  # the comparison saw real observations


def test_batching_does_not_change_the_running_average():
    cameras = _cube_corner_cameras(size=32)
    depths, rgbs = _render_sphere(cameras, background=5.0)
    config = TSDFConfig(resolution=24, truncation=0.1)
    all_at_once = integrate(tsdf_volume(AABB, config), cameras, depths, rgbs)
    one_by_one = tsdf_volume(AABB, config)
    for c in range(len(cameras)):
        integrate(one_by_one, cameras[c], depths[c : c + 1], rgbs[c : c + 1], chunk=1000)
    for name in ("tsdf", "weight", "color", "color_weight"):
        torch.testing.assert_close(
            getattr(one_by_one, name), getattr(all_at_once, name), rtol=1e-5, atol=1e-6
        )


def test_sample_colors_reproduces_a_linear_field():
    volume = tsdf_volume(AABB, TSDFConfig(resolution=8))
    ((_, points),) = grid_slabs(volume.origin, volume.voxel_size, volume.shape, 10**9)
    volume.color.view(-1, 3)[:] = 0.3 * points + 0.2
    volume.color_weight.fill_(1.0)
    query = torch.tensor([[0.05, 0.1, -0.3], [0.6, -0.7, 0.8]])
    torch.testing.assert_close(sample_colors(volume, query), 0.3 * query + 0.2)


@pytest.mark.parametrize("background", [0.0, 6.0])  # misses: no data / far background
def test_fused_sphere_within_a_voxel(background):
    cameras = _cube_corner_cameras()
    depths, rgbs = _render_sphere(cameras, background)
    config = TSDFConfig(resolution=64, truncation=0.05)
    mesh = fuse_depth_maps(
        cameras.to(dtype=torch.float32), depths.float(), rgbs.float(), AABB, config
    )
    h = (AABB[1] - AABB[0]).max() / 64
    radius = np.linalg.norm(mesh.vertices - CENTER.numpy(), axis=1)
    assert np.abs(radius - RADIUS).max() < h
    assert np.abs(radius - RADIUS).mean() < 0.2 * h
    assert mesh.is_watertight
    outward = np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles_center - CENTER.numpy())
    assert (outward > 0).all()
    expected = np.clip((mesh.vertices - CENTER.numpy()) / (2 * RADIUS) + 0.5, 0, 1) * 255
    assert np.abs(mesh.visual.vertex_colors[:, :3] - expected).mean() < 8  # ~3 % of full scale


def test_nothing_observed_gives_empty_mesh():
    volume = tsdf_volume(AABB, TSDFConfig(resolution=8))
    assert len(tsdf_mesh(volume).faces) == 0
