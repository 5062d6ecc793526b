"""Geometry metrics against ground truth: accuracy, completeness, Chamfer, precision / recall /
F-score at a threshold tau, normal consistency (Knapitsch et al. 2017, "Tanks and Temples", Sec. 4).

Distances are Euclidean (not squared), in the units of the inputs; nearest neighbours by
scipy's cKDTree. Meshes are compared through points sampled uniformly by area.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import trimesh


def sample_surface(mesh: trimesh.Trimesh, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n points uniformly by area on a mesh -> points (n, 3), unit face normals (n, 3)."""
    import trimesh  # here, not at the top: image-only callers (train, render) skip its 0.6 s import

    points, face_index = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(points, np.float64), np.asarray(mesh.face_normals[face_index], np.float64)


def nearest_neighbors(query: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each query point (N, 3): distance (N,) to and index (N,) of its nearest reference."""
    from scipy.spatial import cKDTree

    distance, index = cKDTree(reference).query(query, k=1, workers=-1)
    return distance, index


def precision_recall_fscore(
    dist_pred_to_gt: np.ndarray, dist_gt_to_pred: np.ndarray, tau: float
) -> dict[str, float]:
    """P = frac(d(pred -> gt) < tau), R = frac(d(gt -> pred) < tau), F = 2PR / (P + R)
    (Knapitsch et al. 2017, Tanks and Temples). F = 0 when P + R = 0."""
    precision = float(np.mean(dist_pred_to_gt < tau))
    recall = float(np.mean(dist_gt_to_pred < tau))
    total = precision + recall
    fscore = 2 * precision * recall / total if total > 0 else 0.0
    return {"precision": precision, "recall": recall, "fscore": fscore}


def point_cloud_metrics(
    pred_points: np.ndarray,
    gt_points: np.ndarray,
    tau: float,
    pred_normals: np.ndarray | None = None,
    gt_normals: np.ndarray | None = None,
    gt_observed: np.ndarray | None = None,
) -> dict[str, float]:
    """Metrics of a predicted point set (N, 3) against ground truth (M, 3).

    accuracy = mean_p min_g |p - g| (pred -> gt), completeness = mean_g min_p |g - p|
    (gt -> pred), chamfer = (accuracy + completeness) / 2, precision / recall / fscore at tau,
    and, when both normal sets (N, 3), (M, 3) are given, normal_consistency =
    (mean_p |n_p . n_gt(nn(p))| + mean_g |n_g . n_pred(nn(g))|) / 2 (Mescheder et al. 2019),
    1 for matching surfaces; the absolute value ignores orientation flips.

    gt_observed (M,) bool, when given, restricts the gt -> pred side (completeness, recall, its
    half of the normal consistency) to the ground truth some camera saw (as DTU's observation
    masks do): a surface no view saw cannot be asked of a reconstruction. The pred -> gt side
    still measures against all of the ground truth.
    """
    pred_points = np.asarray(pred_points, np.float64).reshape(-1, 3)
    gt_points = np.asarray(gt_points, np.float64).reshape(-1, 3)
    if len(pred_points) == 0 or len(gt_points) == 0:
        raise ValueError("point_cloud_metrics: both point sets must be non-empty")
    d_pred, nn_pred = nearest_neighbors(pred_points, gt_points)
    query = gt_points if gt_observed is None else gt_points[gt_observed]
    if len(query) == 0:
        raise ValueError("point_cloud_metrics: no ground-truth point is observed")
    d_gt, nn_gt = nearest_neighbors(query, pred_points)
    out = {
        "accuracy": float(d_pred.mean()),
        "completeness": float(d_gt.mean()),
        "chamfer": float((d_pred.mean() + d_gt.mean()) / 2),
        "tau": float(tau),
        **precision_recall_fscore(d_pred, d_gt, tau),
    }
    if pred_normals is not None and gt_normals is not None:
        n_pred = _unit(np.asarray(pred_normals, np.float64).reshape(-1, 3))
        n_gt = _unit(np.asarray(gt_normals, np.float64).reshape(-1, 3))
        acc_nc = np.abs((n_pred * n_gt[nn_pred]).sum(-1)).mean()
        n_query = n_gt if gt_observed is None else n_gt[gt_observed]
        comp_nc = np.abs((n_query * n_pred[nn_gt]).sum(-1)).mean()
        out["normal_consistency"] = float((acc_nc + comp_nc) / 2)
    return out


def surface_points(geometry, n_samples: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (N, 3) and normals (N, 3) or None from a mesh (sampled by area), a point cloud
    or an (N, 3) array (used as given)."""
    import trimesh

    if isinstance(geometry, trimesh.Trimesh) and len(geometry.faces) > 0:
        return sample_surface(geometry, n_samples, seed=seed)
    if isinstance(geometry, (trimesh.Trimesh, trimesh.PointCloud)):
        return np.asarray(geometry.vertices, np.float64), None
    return np.asarray(geometry, np.float64).reshape(-1, 3), None


def observed_by_depth(
    points: np.ndarray,
    cam_from_points: np.ndarray,
    K: np.ndarray,
    depths: list[np.ndarray],
    tol: float,
) -> np.ndarray:
    """(M,) bool: points (M, 3) that some view sees, by its ground-truth z-depth map.

    Point x is seen by view c when x_c = cam_from_points_c x (4 x 4, any similarity) lands in
    front of the camera, inside the image, on a pixel with depth D > 0 and |D - z(x_c)| < tol
    (the pixel containing K x_c / z; pixel centres at +0.5). Occluded points lie farther than
    D, unseen ones project outside every image. depths: C maps (H_c, W_c) in the same units.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    seen = np.zeros(len(points), bool)
    for m, k, depth in zip(cam_from_points, K, depths):
        x_cam = points @ m[:3, :3].T + m[:3, 3]
        z = x_cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (x_cam @ np.asarray(k).T)[:, :2] / z[:, None]
        h, w = depth.shape
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        u = np.where(inside, uv[:, 0], 0).astype(np.int64)
        v = np.where(inside, uv[:, 1], 0).astype(np.int64)
        d = depth[v, u]
        seen |= inside & (d > 0) & (np.abs(d - z) < tol)
    return seen


def geometry_metrics(
    pred, gt, tau: float, n_samples: int = 100_000, seed: int = 0, gt_observed_fn=None
) -> dict:
    """`point_cloud_metrics` of two meshes / point clouds / arrays; meshes are sampled with
    n_samples area-uniform points and their face normals (normal consistency then reported).
    gt_observed_fn: gt points (M, 3) -> (M,) bool (e.g. `observed_by_depth`), or None (all).

    Sampling adds an error of the order of the sample spacing ~ sqrt(area / n_samples) even
    for identical meshes: choose n_samples so that it is well below tau.
    """
    pred_points, pred_normals = surface_points(pred, n_samples, seed=seed)
    gt_points, gt_normals = surface_points(gt, n_samples, seed=seed + 1)
    observed = None if gt_observed_fn is None else gt_observed_fn(gt_points)
    out = point_cloud_metrics(pred_points, gt_points, tau, pred_normals, gt_normals, observed)
    out["n_pred_points"], out["n_gt_points"] = len(pred_points), len(gt_points)
    if observed is not None:
        out["gt_observed_fraction"] = float(observed.mean())
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
