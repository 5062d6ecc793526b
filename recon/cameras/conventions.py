"""Conversions at the import/export edge: OpenGL/Blender camera-to-world matrices and
COLMAP quaternions to and from our OpenCV `cam_from_world`."""

from __future__ import annotations

import numpy as np

# OpenGL camera axes (x right, y up, z backward) -> OpenCV (x right, y down, z forward).
OPENCV_FROM_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def opencv_c2w_from_opengl_c2w(world_from_glcam: np.ndarray) -> np.ndarray:
    """(..., 4, 4) OpenGL camera-to-world -> OpenCV camera-to-world (flip y and z axes)."""
    return world_from_glcam @ OPENCV_FROM_OPENGL


def opengl_c2w_from_opencv_c2w(world_from_cam: np.ndarray) -> np.ndarray:
    """Inverse of `opencv_c2w_from_opengl_c2w` (the flip is its own inverse)."""
    return world_from_cam @ OPENCV_FROM_OPENGL


def rotation_from_quat_wxyz(q: np.ndarray) -> np.ndarray:
    """Unit quaternion (..., 4) as (w, x, y, z) -> rotation (..., 3, 3). Normalises first."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    R = np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return R.reshape(q.shape[:-1] + (3, 3))


def quat_wxyz_from_rotation(R: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) -> unit quaternion (w, x, y, z) with w >= 0 (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    m = [R[0, 0] + R[1, 1] + R[2, 2], R[0, 0], R[1, 1], R[2, 2]]
    i = int(np.argmax(m))
    if i == 0:
        s = 2.0 * np.sqrt(1.0 + m[0])
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif i == 1:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif i == 2:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    return q if q[0] >= 0 else -q


def quat_xyzw_from_wxyz(q: np.ndarray) -> np.ndarray:
    """COLMAP's text/binary files store (w, x, y, z); pycolmap 4.x `Rotation3d.quat` is xyzw."""
    return np.roll(np.asarray(q), -1, axis=-1)


def quat_wxyz_from_xyzw(q: np.ndarray) -> np.ndarray:
    return np.roll(np.asarray(q), 1, axis=-1)
