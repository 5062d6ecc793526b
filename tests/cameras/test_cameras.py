import numpy as np
import pytest
import torch

from recon.cameras import Cameras, camera_rays, project_points, unproject_pixels
from recon.cameras.cameras import intrinsics_matrix, invert_rigid
from recon.cameras.conventions import (
    opencv_c2w_from_opengl_c2w,
    opengl_c2w_from_opencv_c2w,
    quat_wxyz_from_rotation,
    quat_wxyz_from_xyzw,
    quat_xyzw_from_wxyz,
    rotation_from_quat_wxyz,
)


def K_problem1():
    return intrinsics_matrix(
        *(torch.tensor(v, dtype=torch.float64) for v in (800.0, 800.0, 320.0, 240.0))
    )


def test_pinhole_projection_worked_example_exact():
    K = K_problem1()
    uv4, z4 = project_points(torch.tensor([0.5, -0.3, 4.0], dtype=torch.float64), K)
    uv8, _ = project_points(torch.tensor([0.5, -0.3, 8.0], dtype=torch.float64), K)
    assert uv4.tolist() == [420.0, 180.0] and z4.item() == 4.0
    assert uv8.tolist() == [370.0, 210.0]
    assert torch.linalg.norm(uv4 - uv8).item() == pytest.approx(58.3095, abs=1e-4)  # sqrt(3400)


def test_project_unproject_round_trip_batched():
    g = torch.Generator().manual_seed(0)
    K = intrinsics_matrix(
        *(torch.rand(5, generator=g, dtype=torch.float64) * 500 + 100 for _ in range(4))
    )
    pts = torch.randn(5, 7, 3, generator=g, dtype=torch.float64)
    pts[..., 2] = pts[..., 2].abs() + 0.5
    uv, z = project_points(pts, K[:, None])
    back = unproject_pixels(uv, z, K[:, None])
    assert torch.allclose(back, pts, atol=1e-10)


def test_rays_pass_through_pixel_centres():
    K = K_problem1()
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, 3] = torch.tensor([0.1, 0.2, 0.3])
    cams = Cameras(K[None], invert_rigid(w2c)[None], torch.tensor([640]), torch.tensor([480]))
    o, d, z_per_t = camera_rays(cams, 0)
    assert o.shape == (480, 640, 3) and torch.allclose(
        d.norm(dim=-1), torch.ones(480, 640, dtype=torch.float64)
    )
    # a point along the ray of pixel (row 180, col 420) projects to its centre (420.5, 180.5)
    t = 3.0
    p_world = o[180, 420] + t * d[180, 420]
    p_cam = p_world - w2c[:3, 3]
    uv, depth = project_points(p_cam, K)
    assert torch.allclose(uv, torch.tensor([420.5, 180.5], dtype=torch.float64), atol=1e-9)
    assert depth.item() == pytest.approx(t * z_per_t[180, 420].item())


def test_opengl_opencv_conversion():
    rng = np.random.default_rng(1)
    R = rotation_from_quat_wxyz(rng.normal(size=4))
    c2w_gl = np.eye(4)
    c2w_gl[:3, :3], c2w_gl[:3, 3] = R, rng.normal(size=3)
    c2w_cv = opencv_c2w_from_opengl_c2w(c2w_gl)
    # OpenGL looks down -z, OpenCV down +z: same optical axis, y flipped
    assert np.allclose(c2w_cv[:3, 2], -c2w_gl[:3, 2]) and np.allclose(c2w_cv[:3, 1], -c2w_gl[:3, 1])
    assert np.allclose(c2w_cv[:3, 3], c2w_gl[:3, 3])
    assert np.allclose(opengl_c2w_from_opencv_c2w(c2w_cv), c2w_gl)


def test_quaternion_conversions_match_pycolmap_xyzw():
    import zlib  # noqa: F401  (before pycolmap, see recon/__init__.py)

    import pycolmap

    rng = np.random.default_rng(2)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        R = rotation_from_quat_wxyz(q)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(
            1.0
        )
        q_back = quat_wxyz_from_rotation(R)
        assert np.allclose(q_back, q * np.sign(q[0]), atol=1e-10)
        rot = pycolmap.Rotation3d(quat_xyzw_from_wxyz(q))
        assert np.allclose(rot.matrix(), R, atol=1e-10)
        assert np.allclose(
            quat_wxyz_from_xyzw(np.asarray(rot.quat)) * np.sign(rot.quat[3]), q * np.sign(q[0])
        )


def test_cameras_scaled_keeps_pixel_edges():
    K = K_problem1()[None].float()
    cams = Cameras(K, torch.eye(4)[None], torch.tensor([640]), torch.tensor([480]))
    half = cams.scaled(0.5)
    assert half.width.item() == 320 and half.height.item() == 240
    # the image centre (pixel edge coordinates) maps to the centre
    uv, _ = project_points(torch.tensor([0.0, 0.0, 1.0]), half.K[0])
    assert uv.tolist() == [160.0, 120.0]


def test_scale_intrinsics_worked_example():
    from recon.cameras.cameras import scale_intrinsics

    K = intrinsics_matrix(
        *(torch.tensor(v, dtype=torch.float64) for v in (1385.3, 1385.3, 538.0, 956.5))
    )
    K4 = scale_intrinsics(K, 269 / 1076, 478 / 1913)
    assert K4[0, 0].item() == pytest.approx(346.325) and K4[0, 2].item() == pytest.approx(134.5)
    assert K4[1, 1].item() == pytest.approx(1385.3 * 478 / 1913) and K4[
        1, 2
    ].item() == pytest.approx(239.0, abs=0.07)


def test_resized_pixel_centres_are_the_centres_of_the_pixel_blocks():
    """An area-downsampled pixel averages a K x K block of the full image: the ray through its
    centre must be the ray through the centre of that block (the +0.5 convention kept)."""
    K = intrinsics_matrix(
        *(torch.tensor(v, dtype=torch.float64) for v in (500.0, 520.0, 311.3, 205.7))
    )
    cams = Cameras(
        K[None], torch.eye(4, dtype=torch.float64)[None], torch.tensor([640]), torch.tensor([480])
    )
    level = cams.resized(160, 120)  # K = 4
    _, d_l, _ = camera_rays(level, 0)  # (120, 160, 3)
    _, d_f, _ = camera_rays(cams, 0)
    # the block of level pixel (row 7, col 11) is full rows 28-31, cols 44-47, i.e. [44, 48) x
    # [28, 32) in edge coordinates: its centre is u = 46, v = 30 (the corner of 4 full pixels)
    uv = torch.tensor([[46.0, 30.0]], dtype=torch.float64)
    from recon.cameras.rays import rays_from_pixels

    _, d_block, _ = rays_from_pixels(uv, K, torch.eye(4, dtype=torch.float64))
    assert torch.allclose(d_l[7, 11], d_block[0], atol=1e-12)
    assert not torch.allclose(d_f[7, 11], d_block[0], atol=1e-3)  # (sanity: another ray)
    assert level.width.item() == 160 and level.height.item() == 120


def test_centres_are_the_inverse_transforms_translations():
    """o = -R^T t: the translation of world_from_cam, and the point the camera maps to its
    origin. Worked example: R a quarter turn about z, t = (1, 2, 3) -> o = (-2, 1, -3)."""
    R = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    M = torch.eye(4)
    M[:3, :3], M[:3, 3] = R, torch.tensor([1.0, 2, 3])
    gen = torch.Generator().manual_seed(0)
    q = torch.linalg.qr(torch.randn(3, 3, 3, generator=gen, dtype=torch.float64))[0]
    many = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    many[:, :3, :3], many[:, :3, 3] = q, torch.randn(3, 3, generator=gen, dtype=torch.float64)
    for cfw in (M[None], many):
        cams = Cameras(torch.eye(3, dtype=cfw.dtype).expand(len(cfw), 3, 3), cfw,
                       torch.full((len(cfw),), 4), torch.full((len(cfw),), 3))  # fmt: skip
        torch.testing.assert_close(cams.centers, invert_rigid(cfw)[:, :3, 3])
        origin = (cfw[:, :3, :3] @ cams.centers[..., None])[..., 0] + cfw[:, :3, 3]
        torch.testing.assert_close(origin, torch.zeros_like(origin), atol=1e-6, rtol=0)
    torch.testing.assert_close(Cameras(torch.eye(3)[None], M[None], torch.tensor([4]),
                               torch.tensor([3])).centers, torch.tensor([[-2.0, 1, -3]]))  # fmt: skip
