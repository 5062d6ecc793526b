"""Scene normalization (SPEC §3): a similarity `scene_from_world` that puts the cameras and
the robust bulk of the sparse points inside [-1, 1]^3, +z up, and the box of interest."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Similarity:
    """x_scene = scale * R @ x_world + t."""

    scale: float
    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,)

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * points @ self.R.T + self.t

    def invert_points(self, points_scene: np.ndarray) -> np.ndarray:
        """x_world = R^T (x_scene - t) / scale."""
        return ((points_scene - self.t) / self.scale) @ self.R

    def world_from_cam_to_scene(self, world_from_cam: np.ndarray) -> np.ndarray:
        """(C, 4, 4) world_from_cam -> scene_from_cam (rigid: the scale moves the centre only)."""
        out = world_from_cam.copy()
        out[:, :3, :3] = self.R @ world_from_cam[:, :3, :3]
        out[:, :3, 3] = self.apply(world_from_cam[:, :3, 3])
        return out

    def to_json(self) -> dict:
        return {"scale": float(self.scale), "R": self.R.tolist(), "t": self.t.tolist()}

    @staticmethod
    def from_json(d: dict) -> Similarity:
        return Similarity(float(d["scale"]), np.asarray(d["R"], float), np.asarray(d["t"], float))


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


def normalize_scene(world_from_cam: np.ndarray, K: np.ndarray, sizes: np.ndarray,
                    points: np.ndarray | None, margin: float = 0.9) -> tuple[Similarity, np.ndarray]:
    """Choose `scene_from_world` and the box of interest (aabb, scene frame).

    Up: the mean camera up vector (-y in OpenCV) becomes +z. Centre: the centre of the robust
    point box, else the optical axes' meeting point. Scale: cameras and the robust box fit in
    [-margin, margin]^3. The aabb is the robust point box padded by 10 %, else the cube that
    the median camera sees around the look-at point (half-size = distance * tan(half fov)).
    """
    up = -world_from_cam[:, :3, 1].mean(0)
    R = rotation_between(up, np.array([0.0, 0.0, 1.0])) if np.linalg.norm(up) > 1e-6 else np.eye(3)
    if points is not None and len(points) >= 10:
        box = robust_box(points @ R.T)
        center = box.mean(0)
        pad = 0.1 * (box[1] - box[0]).max()
        aabb_rot = np.stack([box[0] - pad, box[1] + pad])
    else:
        center = R @ look_at_point(world_from_cam)
        dist = np.median(np.linalg.norm(world_from_cam[:, :3, 3] - R.T @ center, axis=1))
        half_fov = np.arctan(0.5 * np.median(np.minimum(sizes[:, 0] / K[:, 0, 0], sizes[:, 1] / K[:, 1, 1])))
        half = dist * np.tan(half_fov)
        aabb_rot = np.stack([center - half, center + half])
    cams_rot = world_from_cam[:, :3, 3] @ R.T
    extent = max(np.abs(cams_rot - center).max(), np.abs(aabb_rot - center).max())
    scale = margin / extent
    sim = Similarity(scale, R, -scale * center)
    aabb = np.clip((aabb_rot - center) * scale, -1.0, 1.0)
    return sim, aabb
