import itertools

import numpy as np
import pytest
import trimesh
from scipy.spatial.distance import cdist

from recon.metrics.geometry import (
    geometry_metrics,
    nearest_neighbors,
    observed_by_depth,
    point_cloud_metrics,
    precision_recall_fscore,
)


def _sphere_points(n: int, radius: float, seed: int) -> np.ndarray:
    d = np.random.default_rng(seed).standard_normal((n, 3))
    return radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def test_nearest_neighbors_matches_brute_force():
    rng = np.random.default_rng(0)
    q, r = rng.random((300, 3)), rng.random((200, 3))
    dist, idx = nearest_neighbors(q, r)
    full = cdist(q, r)
    np.testing.assert_allclose(dist, full.min(axis=1), rtol=1e-12)
    np.testing.assert_array_equal(idx, full.argmin(axis=1))


def test_hand_example():
    pred = np.array([[0.0, 0, 0], [1, 0, 0]])
    gt = np.array([[0.0, 0, 0]])
    out = point_cloud_metrics(pred, gt, tau=0.5)
    assert out["accuracy"] == pytest.approx(0.5)  # (0 + 1) / 2
    assert out["completeness"] == pytest.approx(0.0)
    assert out["chamfer"] == pytest.approx(0.25)
    assert out["precision"] == 0.5 and out["recall"] == 1.0
    assert out["fscore"] == pytest.approx(2 * 0.5 * 1.0 / 1.5)


def test_normal_consistency_hand_example():
    # one point each, normals 60 degrees apart -> |cos 60| = 0.5 both ways
    n_pred = np.array([[np.cos(np.pi / 3), np.sin(np.pi / 3), 0.0]])
    out = point_cloud_metrics(np.zeros((1, 3)), np.zeros((1, 3)), 0.1, n_pred, [[1.0, 0, 0]])
    assert out["normal_consistency"] == pytest.approx(0.5)


def test_same_samples_are_perfect():
    p = _sphere_points(2000, 1.0, 1)
    out = point_cloud_metrics(p, p, tau=1e-3, pred_normals=p, gt_normals=-p)  # flips ignored
    assert out["chamfer"] == 0.0 and out["fscore"] == 1.0
    assert out["normal_consistency"] == pytest.approx(1.0)


def test_mesh_with_itself_bounded_by_sampling_density():
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    n = 20_000
    out = geometry_metrics(mesh, mesh, tau=0.05, n_samples=n, seed=3)  # different samples
    spacing = np.sqrt(mesh.area / n)
    assert 0 < out["chamfer"] < spacing
    assert out["fscore"] > 0.99
    assert out["normal_consistency"] > 0.99


@pytest.mark.parametrize("eps", [0.01, 0.05])
def test_concentric_spheres_chamfer_is_eps(eps):
    # Same directions on radii r and r + eps: every nearest neighbour is exactly eps away.
    p = _sphere_points(5000, 1.0, 4)
    out = point_cloud_metrics(p, p * (1 + eps), tau=eps / 2)
    assert out["chamfer"] == pytest.approx(eps, rel=1e-9)
    assert out["fscore"] == 0.0  # every distance is eps > tau
    # Meshes, independently sampled: eps up to sampling + faceting error.
    inner = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    outer = trimesh.creation.icosphere(subdivisions=5, radius=1.0 + eps)
    meshes = geometry_metrics(inner, outer, tau=eps / 2, n_samples=20_000)
    assert meshes["chamfer"] == pytest.approx(eps, abs=0.01)


def test_fscore_monotone_in_tau():
    pred = _sphere_points(3000, 1.0, 5) + 0.02 * np.random.default_rng(6).standard_normal((3000, 3))
    gt = _sphere_points(3000, 1.0, 7)
    d_pred, _ = nearest_neighbors(pred, gt)
    d_gt, _ = nearest_neighbors(gt, pred)
    taus = [0.001, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2]
    f = [precision_recall_fscore(d_pred, d_gt, t)["fscore"] for t in taus]
    assert all(a <= b for a, b in itertools.pairwise(f))
    assert f[0] < 0.2 and f[-1] == 1.0


def test_point_cloud_and_array_inputs_skip_normals():
    p = _sphere_points(500, 1.0, 8)
    out = geometry_metrics(trimesh.PointCloud(p), p, tau=0.01)
    assert out["chamfer"] == 0.0 and "normal_consistency" not in out
    with pytest.raises(ValueError):
        point_cloud_metrics(np.zeros((0, 3)), p, tau=0.1)


def test_observed_by_depth_worked_example():
    # a camera at the origin looking down +z, f = 10, c = (5, 5), 10 x 10 px, a wall at z = 2
    K = np.array([[[10.0, 0, 5], [0, 10, 5], [0, 0, 1]]])
    depth = [np.full((10, 10), 2.0)]
    depth[0][:, 8:] = 0.0  # no surface in the last two columns
    points = np.array(
        [
            [0, 0, 2.0],  # on the wall: seen
            [0, 0, 3.0],  # behind the wall: occluded
            [0, 0, -1.0],  # behind the camera
            [100, 0, 2.0],  # outside the image
            [0.35, 0, 2.0],
        ]
    )  # pixel column 6.75 -> 6: seen; 0.65 -> column 8: no depth
    expected = [True, False, False, False, True]
    np.testing.assert_array_equal(
        observed_by_depth(points, np.eye(4)[None], K, depth, tol=0.1), expected
    )
    assert not observed_by_depth(np.array([[0.65, 0, 2.0]]), np.eye(4)[None], K, depth, tol=0.1)[0]
    # the same in units twice as small: a similarity x_cam = 2 x (depths stay in camera units)
    half = np.diag([2.0, 2.0, 2.0, 1.0])[None]
    np.testing.assert_array_equal(observed_by_depth(points / 2, half, K, depth, tol=0.1), expected)


def test_unobserved_ground_truth_leaves_recall():
    seen = np.random.default_rng(0).uniform(0, 1, (500, 3))
    unseen = seen + np.array([5.0, 0, 0])  # e.g. the underside nobody photographed
    gt = np.concatenate([seen, unseen])
    observed = np.arange(len(gt)) < len(seen)
    full = point_cloud_metrics(seen, gt, tau=0.01)
    masked = point_cloud_metrics(seen, gt, tau=0.01, gt_observed=observed)
    assert full["recall"] == 0.5 and masked["recall"] == 1.0
    assert masked["precision"] == full["precision"] == 1.0 and masked["completeness"] == 0.0
