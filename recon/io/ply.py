"""Binary little-endian PLY point clouds (positions + optional uint8 colours)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon.io.atomic import atomic_path


def write_points_ply(path: Path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """points (N, 3) float; colors (N, 3) uint8 or float in [0, 1]."""
    points = np.asarray(points, dtype=np.float32)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        colors = np.asarray(colors)
        if colors.dtype != np.uint8:
            colors = (np.clip(colors, 0, 1) * 255 + 0.5).astype(np.uint8)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    arr = np.empty(len(points), dtype=fields)
    arr["x"], arr["y"], arr["z"] = points.T
    if colors is not None:
        arr["red"], arr["green"], arr["blue"] = colors.T
    types = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(points)}"]
    header += [f"property {types[t]} {n}" for n, t in fields] + ["end_header"]
    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode())
        f.write(arr.tobytes())


def read_points_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a PLY point cloud -> points (N, 3) float32, colours (N, 3) float32 in [0, 1] or None."""
    import trimesh

    cloud = trimesh.load(str(path), process=False)
    points = np.asarray(cloud.vertices, dtype=np.float32)
    colors = getattr(cloud, "colors", None)
    if colors is None or len(colors) != len(points):
        colors = getattr(getattr(cloud, "visual", None), "vertex_colors", None)
    if colors is None or len(colors) != len(points):
        return points, None
    return points, np.asarray(colors, dtype=np.float32)[:, :3] / 255.0
