"""The cross-view depth check: exact depth maps of one plane agree everywhere they overlap; a
wrong patch in one view is voted out; the fused point is the plane's."""

import pytest
import torch

from recon.cameras import Cameras
from recon.cameras.rays import pixel_centers, unproject_pixels
from recon.mvs.consistency import consistent_views, depth_to_world
from recon.mvs.stage import box_depth_range, source_views, view_depth_range


def plane_rig(n=3, W=40, H=32, f=40.0, z_plane=2.0):
    """n cameras looking down +z from centres spread along x; z-depth maps of the plane z = 2."""
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]]).expand(n, 3, 3).clone()
    cam_from_world = torch.eye(4).repeat(n, 1, 1)
    cam_from_world[:, 0, 3] = -0.2 * torch.arange(n)  # centres at x = 0, 0.2, 0.4
    cams = Cameras(K, cam_from_world, torch.full((n,), W), torch.full((n,), H))
    return cams, torch.full((n, H, W), z_plane)


def test_depth_to_world_lifts_pixels_onto_the_plane():
    cams, depths = plane_rig()
    points = depth_to_world(depths[1], cams.K[1], cams.world_from_cam[1])
    torch.testing.assert_close(points[..., 2], torch.full_like(points[..., 2], 2.0))
    uv = pixel_centers(40, 32)
    want = unproject_pixels(uv, depths[1], cams.K[1])[..., 0] + 0.2
    torch.testing.assert_close(points[..., 0], want)


def test_exact_depth_maps_agree_where_the_views_overlap():
    cams, depths = plane_rig()
    count, fused = consistent_views(depths, cams, 0)
    # at z = 2 camera 0 sees x in [-1, 1]; camera k, 0.2 k to the right, misses the left
    # 0.2 k f / z = 4 k columns of it
    assert (count[:, :4] == 0).all() and (count[:, 4:8] == 1).all() and (count[:, 8:] == 2).all()
    torch.testing.assert_close(fused[..., 2], torch.full_like(fused[..., 2], 2.0))


def test_a_wrong_patch_is_voted_out_and_the_others_stay():
    cams, depths = plane_rig()
    depths[0, 10:20, 20:30] = 2.3  # 15 % too far: no other view puts the surface there
    count, _ = consistent_views(depths, cams, 0)
    assert (count[10:20, 20:30] == 0).all()
    assert (count[22:, 8:] == 2).all()
    none = depths.clone()
    none[1:] = 0  # views without depth cannot agree
    assert (consistent_views(none, cams, 0)[0] == 0).all()


def test_source_views_are_the_nearest_by_direction():
    yaw = torch.deg2rad(torch.tensor([0.0, 30, 60, 90, 120, 330]))
    R = torch.zeros(6, 3, 3)
    R[:, 0, 0], R[:, 0, 2] = torch.cos(yaw), -torch.sin(yaw)
    R[:, 1, 1] = 1
    R[:, 2, 0], R[:, 2, 2] = torch.sin(yaw), torch.cos(yaw)
    m = torch.eye(4).repeat(6, 1, 1)
    m[:, :3, :3] = R
    cams = Cameras(torch.eye(3).expand(6, 3, 3), m, torch.ones(6), torch.ones(6))
    assert sorted(source_views(cams, 0, 2)) == [1, 5]
    assert source_views(cams, 3, 1) in ([2], [4])


def test_box_depth_range_spans_the_box_corners():
    aabb = torch.tensor([[-1.0, -1, -1], [1, 1, 1]])
    m = torch.eye(4)
    m[2, 3] = 5.0  # the box centre 5 in front of the camera
    assert box_depth_range(aabb, m) == (4.0, 6.0)


def test_view_depth_range_comes_from_the_points_the_view_sees():
    aabb = torch.tensor([[-4.0, -4, -4], [4, 4, 4]])  # the camera sits inside the box
    m = torch.eye(4)
    K = torch.tensor([[10.0, 0, 10], [0, 10, 10], [0, 0, 1]])
    assert view_depth_range(aabb, m, K, (20, 20)) == box_depth_range(aabb, m)
    g = torch.Generator().manual_seed(0)
    seen = torch.cat(
        [torch.rand(200, 2, generator=g) - 0.5, torch.rand(200, 1, generator=g) + 1], 1
    )
    seen[:, :2] *= seen[:, 2:]  # in the view frustum, z-depths uniform in [1, 2]
    behind = seen * torch.tensor([1.0, 1, -1])  # not seen: the camera looks down +z
    near, far = view_depth_range(aabb, m, K, (20, 20), torch.cat([seen, behind]))
    z = seen[:, 2]
    lo, hi = torch.quantile(z, torch.tensor([0.01, 0.99]))
    assert near == pytest.approx(float(lo) / 1.2) and far == pytest.approx(float(hi) * 1.2)
    assert view_depth_range(aabb, m, K, (20, 20), seen[:5]) == box_depth_range(aabb, m)
