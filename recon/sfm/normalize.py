"""Scene normalization: a similarity `scene_from_world` that puts the cameras and
the robust bulk of the sparse points inside [-1, 1]^3, +z up, and the box of interest."""

from __future__ import annotations

import numpy as np

from recon.cameras.similarity import Similarity


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation R with R a = b for unit vectors a, b (Rodrigues)."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-9:  # opposite: rotate pi about any axis orthogonal to a
        axis = np.cross(a, [1.0, 0, 0]) if abs(a[0]) < 0.9 else np.cross(a, [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def look_at_point(world_from_cam: np.ndarray) -> np.ndarray:
    """Least-squares point closest to every optical axis (where an object-centric capture looks)."""
    centers, axes = world_from_cam[:, :3, 3], world_from_cam[:, :3, 2]
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centers, axes):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    if np.linalg.cond(A) > 1e8:  # all axes parallel: forward-facing capture
        return centers.mean(0) + axes.mean(0) * np.linalg.norm(centers.std(0)) * 2
    return np.linalg.solve(A, b)


def robust_box(points: np.ndarray, lo: float = 2.0, hi: float = 98.0) -> np.ndarray:
    """(2, 3) per-axis percentile box of the bulk of a point cloud."""
    return np.stack([np.percentile(points, lo, axis=0), np.percentile(points, hi, axis=0)])


def depth_points(
    world_from_cam: np.ndarray, K: np.ndarray, depths: list[np.ndarray], stride: int = 4
) -> np.ndarray:
    """World points (N, 3) of z-depth maps: x_world = world_from_cam [z K^-1 (u, v, 1)], at every
    stride-th pixel centre (u, v) = (i + 0.5, j + 0.5); depth <= 0 or non-finite = no surface.
    world_from_cam (C, 4, 4), K (C, 3, 3), depths C maps (H_c, W_c) in the pose units."""
    out = []
    for w_from_c, k, depth in zip(world_from_cam, K, depths):
        v, u = np.mgrid[0 : depth.shape[0] : stride, 0 : depth.shape[1] : stride]
        z = depth[v, u].astype(np.float64)
        ok = np.isfinite(z) & (z > 0)
        pix = np.stack([u[ok] + 0.5, v[ok] + 0.5, np.ones(ok.sum())], -1)
        x_cam = (pix @ np.linalg.inv(k).T) * z[ok][:, None]
        out.append(x_cam @ w_from_c[:3, :3].T + w_from_c[:3, 3])
    return np.concatenate(out) if out else np.zeros((0, 3))


def carve(
    points: np.ndarray,
    world_from_cam: np.ndarray,
    K: np.ndarray,
    masks: list[np.ndarray],
    min_views: int,
) -> np.ndarray:
    """(N,) bool: the visual hull test (Laurentini 1994) for points (N, 3) world. A point is kept
    when it projects inside the image in >= min_views views and onto the mask (H_c, W_c) bool in
    every one of them; views it falls outside of (or behind) say nothing about it."""
    seen = np.zeros(len(points), np.int64)
    kept = np.ones(len(points), bool)
    for w_from_c, k, mask in zip(world_from_cam, K, masks):
        x_cam = (points - w_from_c[:3, 3]) @ w_from_c[:3, :3]  # R^T (x - c)
        z = x_cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (x_cam @ k.T)[:, :2] / z[:, None]
        h, w = mask.shape
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        u = np.where(inside, uv[:, 0], 0).astype(np.int64)
        v = np.where(inside, uv[:, 1], 0).astype(np.int64)
        seen += inside
        kept &= ~inside | mask[v, u]
    return kept & (seen >= min_views)


def grid_points(box: np.ndarray, n: int) -> tuple[np.ndarray, float]:
    """Centres (n^3, 3) of an n x n x n grid of cubic cells covering box (2, 3) from its centre,
    and the cell size (the longest side / n)."""
    h = float((box[1] - box[0]).max()) / n
    axes = [box.mean(0)[a] + h * (np.arange(n) - (n - 1) / 2) for a in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3), h


def hull_box(
    world_from_cam: np.ndarray,
    K: np.ndarray,
    masks: list[np.ndarray],
    region: np.ndarray,
    resolution: int = 48,
    max_views: int = 40,
) -> np.ndarray | None:
    """(2, 3) world box of the visual hull of the masks inside region (2, 3), or None when nothing
    survives. Two passes (the region, then the first box grown by two cells) of resolution^3
    cell centres; the box is padded by 1.5 cells so cells straddling a silhouette are inside it.
    Views are thinned to max_views (evenly) to bound the cost; a cell must be seen by half of them."""
    keep = np.unique(np.linspace(0, len(masks) - 1, min(len(masks), max_views)).round().astype(int))
    w_from_c, k, m = world_from_cam[keep], K[keep], [masks[i] for i in keep]
    min_views = max(2, (len(keep) + 1) // 2)
    box = np.asarray(region, np.float64)
    for grow in (2.0, 1.5):
        pts, h = grid_points(box, resolution)
        inside = pts[carve(pts, w_from_c, k, m, min_views)]
        if len(inside) == 0:
            return None
        box = np.stack([inside.min(0) - grow * h, inside.max(0) + grow * h])
    return box


def object_box(
    world_from_cam: np.ndarray,
    K: np.ndarray,
    sizes: np.ndarray,
    points: np.ndarray | None,
    depths: list[np.ndarray] | None = None,
    masks: list[np.ndarray] | None = None,
) -> tuple[np.ndarray, str]:
    """(2, 3) world box of the scene content and where it came from, from the best evidence:
    sparse points (robust 2-98 % box), else ground-truth depth maps (0.5-99.5 %), each padded by
    10 % of the longest side; else the visual hull of the alpha masks (when they blank >= 5 % of
    the median view), padded by 5 %; else the cube that the
    median camera sees around the optical axes' meeting point (half-size = distance * tan(half
    fov)), which is too small when the content fills the frames (a plate running off them)."""

    def padded(box, fraction=0.1):
        pad = fraction * (box[1] - box[0]).max()
        return np.stack([box[0] - pad, box[1] + pad])

    if points is not None and len(points) >= 10:
        return padded(robust_box(points)), "points"
    if depths is not None and all(d is not None for d in depths):
        pts = depth_points(world_from_cam, K, depths)
        if len(pts) >= 10:
            return padded(robust_box(pts, 0.5, 99.5)), "depth"
    center = look_at_point(world_from_cam)
    # alpha that only blanks an undistortion border (< 5 % of the median view) bounds nothing
    if masks is not None and np.median([1.0 - m.mean() for m in masks]) >= 0.05:
        reach = np.linalg.norm(world_from_cam[:, :3, 3] - center, axis=1).max()
        box = hull_box(world_from_cam, K, masks, np.stack([center - reach, center + reach]))
        if box is not None:
            return padded(box, 0.05), "masks"
    dist = np.median(np.linalg.norm(world_from_cam[:, :3, 3] - center, axis=1))
    half_fov = np.arctan(
        0.5 * np.median(np.minimum(sizes[:, 0] / K[:, 0, 0], sizes[:, 1] / K[:, 1, 1]))
    )
    half = dist * np.tan(half_fov)
    return np.stack([center - half, center + half]), "cameras"


def normalize_scene(
    world_from_cam: np.ndarray,
    K: np.ndarray,
    sizes: np.ndarray,
    points: np.ndarray | None,
    margin: float = 0.9,
    depths: list[np.ndarray] | None = None,
    masks: list[np.ndarray] | None = None,
) -> tuple[Similarity, np.ndarray]:
    """Choose `scene_from_world` and the box of interest (aabb, scene frame).

    Up: the mean camera up vector (-y in OpenCV) becomes +z. The box: `object_box` (points, else
    depth maps, else alpha masks, else the cameras' view), found in the rotated (z-up) frame.
    Centre: the box centre. Scale: cameras and the box fit in [-margin, margin]^3; the aabb is
    clipped to [-1, 1]^3.
    """
    up = -world_from_cam[:, :3, 1].mean(0)
    R = rotation_between(up, np.array([0.0, 0.0, 1.0])) if np.linalg.norm(up) > 1e-6 else np.eye(3)
    rot_from_cam = world_from_cam.copy()  # the same cameras in the rotated frame
    rot_from_cam[:, :3, :] = R @ world_from_cam[:, :3, :]
    points_rot = None if points is None else points @ R.T
    aabb_rot, _ = object_box(rot_from_cam, K, sizes, points_rot, depths, masks)
    cams_rot = rot_from_cam[:, :3, 3]
    center = aabb_rot.mean(0)
    extent = max(np.abs(cams_rot - center).max(), np.abs(aabb_rot - center).max())
    scale = margin / extent
    sim = Similarity(scale, R, -scale * center)
    aabb = np.clip((aabb_rot - center) * scale, -1.0, 1.0)
    return sim, aabb
