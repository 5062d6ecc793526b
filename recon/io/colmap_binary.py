"""COLMAP's binary sparse-model format (cameras.bin, images.bin, points3D.bin; Schoenberger and
Frahm 2016, the COLMAP documentation's "Binary File Format"), written without COLMAP itself:
imported poses (a transforms.json, a known rig) then need no pycolmap, which a GPU image may
lack. Little-endian throughout; quaternions (w, x, y, z) of cam_from_world, as COLMAP stores
them. Points are written with empty tracks.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

PINHOLE = 1  # COLMAP's camera model id of PINHOLE (fx, fy, cx, cy)


def quat_wxyz(rotation: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> unit quaternion (w, x, y, z) with w >= 0.
    Example: 90 degrees about z -> (0.70711, 0, 0, 0.70711)."""
    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    q = np.array([w, x, y, z])
    return -q if w < 0 else q


def write_colmap_binary(
    out: Path,
    cameras: list[tuple[int, int, int, float, float, float, float]],
    images: list[tuple[int, str, int, np.ndarray]],
    points: np.ndarray | None = None,
    colors: np.ndarray | None = None,
) -> None:
    """Write a PINHOLE model to the folder `out`.
    cameras: (camera_id, width, height, fx, fy, cx, cy); images: (image_id, name, camera_id,
    cam_from_world (3, 4) or (4, 4)); points (P, 3) with colors (P, 3) uint8."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", len(cameras)))
        f.writelines(
            struct.pack("<IiQQ4d", cam_id, PINHOLE, w, h, fx, fy, cx, cy)
            for cam_id, w, h, fx, fy, cx, cy in cameras
        )
    with open(out / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", len(images)))
        for image_id, name, cam_id, cam_from_world in images:
            m = np.asarray(cam_from_world, dtype=np.float64)
            f.write(struct.pack("<I4d3di", image_id, *quat_wxyz(m[:3, :3]), *m[:3, 3], cam_id))
            f.write(name.encode() + b"\0")
            f.write(struct.pack("<Q", 0))  # no 2D points
    points = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=np.float64)
    if colors is None:
        colors = np.full((len(points), 3), 128)
    with open(out / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", len(points)))
        f.writelines(
            struct.pack("<Q3d3BdQ", i, *p, *c, 0.0, 0)
            for i, (p, c) in enumerate(zip(points, np.asarray(colors, dtype=np.uint8)), start=1)
        )
