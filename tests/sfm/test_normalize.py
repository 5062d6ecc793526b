"""Scene box (recon.sfm.normalize): depth back-projection by hand, the visual hull of a sphere
against its exact bounds, and sample_data, whose plate the old camera-view box cut off."""

import json
from pathlib import Path

import numpy as np
import trimesh

from recon.sfm.normalize import carve, depth_points, hull_box, normalize_scene, object_box

ROOT = Path(__file__).resolve().parents[2]


def _ring(n=12, radius=3.0, height=1.0, f=60.0, size=64):
    """n OpenCV cameras on a ring around the origin, looking at it -> (C, 4, 4), (C, 3, 3), sizes."""
    c2w = []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        eye = np.array([radius * np.cos(a), radius * np.sin(a), height])
        fwd = -eye / np.linalg.norm(eye)
        right = np.cross(fwd, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(fwd, right), fwd, eye
        c2w.append(m)
    K = np.tile(np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]]), (n, 1, 1))
    return np.stack(c2w), K, np.full((n, 2), float(size))


def _sphere_masks(c2w, K, size, center, r):
    """Exact silhouettes: pixel centres whose ray passes within r of the centre."""
    v, u = np.mgrid[0:size, 0:size] + 0.5
    masks = []
    for m, k in zip(c2w, K):
        d = (
            np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], -1)
            @ m[:3, :3].T
        )
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        oc = center - m[:3, 3]
        t = d @ oc
        masks.append((np.linalg.norm(oc) ** 2 - t**2 < r**2) & (t > 0))
    return masks


def test_depth_points_worked_example():
    # identity camera, f = 100, c = (50, 50), depth 2 everywhere: pixel (i, j) = (0, 0) has its
    # centre at (0.5, 0.5) -> x = (0.5 - 50) / 100 * 2 = -0.99, same for y, z = 2
    K = np.array([[[100.0, 0, 50], [0, 100, 50], [0, 0, 1]]])
    c2w = np.eye(4)[None].copy()
    c2w[0, :3, 3] = [1.0, 0, 0]  # moved by +1 in x
    depth = np.full((100, 100), 2.0)
    depth[50:, :] = 0.0  # no surface in the lower half
    pts = depth_points(c2w, K, [depth], stride=50)
    np.testing.assert_allclose(pts, [[1 - 0.99, -0.99, 2.0], [1 + 0.01, -0.99, 2.0]])


def test_carve_needs_min_views_and_every_mask():
    c2w, K, _ = _ring(n=8)
    full = [np.ones((64, 64), bool)] * 8
    origin = np.zeros((1, 3))
    assert carve(origin, c2w, K, full, min_views=8)[0]
    assert not carve(origin, c2w, K, full, min_views=9)[0]
    one_empty = [np.zeros((64, 64), bool)] + full[1:]
    assert not carve(origin, c2w, K, one_empty, min_views=1)[0]
    behind_all = np.array([[0.0, 0.0, 100.0]])  # far above: behind or outside every view
    assert not carve(behind_all, c2w, K, full, min_views=1)[0]


def test_hull_box_of_a_sphere_contains_it_and_is_tight():
    c2w, K, _ = _ring(n=16, height=1.5)
    center, r = np.array([0.2, -0.1, 0.3]), 0.5
    box = hull_box(
        c2w, K, _sphere_masks(c2w, K, 64, center, r), np.stack([center - 3.5, center + 3.5])
    )
    assert np.all(box[0] <= center - r) and np.all(box[1] >= center + r), box
    # a ring of views above the equator bounds x, y tightly; z is looser (no view from below)
    assert np.all(box[1, :2] - box[0, :2] < 2 * r * 1.25), box
    assert box[1, 2] - box[0, 2] < 2 * r * 2.0, box


def test_uninformative_masks_fall_back_to_the_camera_view():
    c2w, K, sizes = _ring()
    border = np.ones((64, 64), bool)
    border[:, :1] = False  # 1.6 % blank: an undistortion border
    _, source = object_box(c2w, K, sizes, None, masks=[border] * len(c2w))
    assert source == "cameras"


def test_sample_data_box_contains_the_plate():
    """The plate (radius 1 m) runs off every view; the camera-view cube (half 0.79 m) cut it."""
    from recon.sfm.scene_writer import SceneConfig, prepare_depth, prepare_image
    from recon.sfm.sources import read_transforms

    posed = read_transforms(ROOT / "sample_data" / "transforms.json")
    white = np.ones(3, np.float32)
    Ks, sizes, masks, depths = [], [], [], []
    for frame in posed.frames:
        img, k, mask = prepare_image(frame, SceneConfig(), white)
        Ks.append(k), sizes.append(img.shape[1::-1]), masks.append(mask)
        depths.append(prepare_depth(frame, img.shape[1], img.shape[0]))
    c2w = np.stack([f.world_from_cam for f in posed.frames])
    Ks, sizes = np.stack(Ks), np.array(sizes, float)
    gt = trimesh.load(ROOT / "sample_data" / "mesh.ply")
    for kwargs, source in (({"depths": depths}, "depth"), ({"masks": masks}, "masks")):
        box, got = object_box(c2w, Ks, sizes, None, **kwargs)
        assert got == source
        assert np.all(box[0] <= gt.bounds[0]) and np.all(box[1] >= gt.bounds[1]), (
            source,
            box,
            gt.bounds,
        )
    # depth bounds the visible surfaces tightly; silhouettes seen only from above cannot bound
    # the space under a plate that runs off the views, so the hull box is loose there
    box, _ = object_box(c2w, Ks, sizes, None, depths=depths, masks=masks)
    assert np.all(box[1] - box[0] < 1.3 * (gt.bounds[1] - gt.bounds[0]).max()), box
    old, _ = object_box(c2w, Ks, sizes, None)
    assert not (np.all(old[0] <= gt.bounds[0]) and np.all(old[1] >= gt.bounds[1]))
    sim, aabb = normalize_scene(c2w, Ks, sizes, None, depths=depths, masks=masks)
    inside = sim.apply(np.asarray(gt.vertices))
    assert np.all(inside >= aabb[0]) and np.all(inside <= aabb[1])
    assert np.abs(sim.apply(c2w[:, :3, 3])).max() <= 0.9 + 1e-9
    assert (
        json.loads((ROOT / "sample_data" / "transforms.json").read_text())["gt_mesh_path"]
        == "mesh.ply"
    )
