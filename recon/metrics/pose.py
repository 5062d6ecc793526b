"""Camera-pose accuracy against reference poses: Sim3 alignment of camera centres (ATE) and
per-camera rotation / centre errors.

SfM recovers poses only up to a similarity (scale, rotation, translation of the world), so
estimated poses are first mapped into the reference frame by the least-squares Sim3 of the
camera centres (Umeyama 1991), then compared camera by camera.
"""

from __future__ import annotations

import numpy as np


def umeyama(
    src: np.ndarray, dst: np.ndarray, with_scale: bool = True
) -> tuple[float, np.ndarray, np.ndarray]:
    """Closed-form similarity  argmin_{s,R,t} sum_i ||dst_i - (s R src_i + t)||^2  (Umeyama 1991).

    With centred points x_i = src_i - mean(src), y_i = dst_i - mean(dst), the cross-covariance
    Sigma = (1/N) sum_i y_i x_i^T = U D V^T gives R = U S V^T with S = diag(1, 1, det(U) det(V))
    (the reflection fix: S flips the weakest axis when the best orthogonal map is a mirror),
    s = tr(D S) / ((1/N) sum_i ||x_i||^2) and t = mean(dst) - s R mean(src).

    Example: dst = 2 * src + [1, 0, 0] gives (s, R, t) = (2, I, [1, 0, 0]).

    src, dst: (N, 3) with N >= 3 points not all on one line. Returns (s, R (3, 3), t (3,)); s = 1
    when `with_scale` is False (a rigid fit).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or src.shape[0] < 3:
        raise ValueError(
            f"umeyama needs two (N, 3) arrays with N >= 3, got {src.shape} and {dst.shape}"
        )
    mu_src, mu_dst = src.mean(axis=0), dst.mean(axis=0)
    x, y = src - mu_src, dst - mu_dst
    sigma = y.T @ x / len(src)
    U, D, Vt = np.linalg.svd(sigma)
    S = np.ones(3)
    S[2] = np.sign(np.linalg.det(U) * np.linalg.det(Vt)) or 1.0
    R = (U * S) @ Vt
    var_src = np.mean(np.sum(x * x, axis=1))
    s = float(np.sum(D * S) / var_src) if with_scale else 1.0
    t = mu_dst - s * R @ mu_src
    return s, R, t


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Geodesic angle of rotations (..., 3, 3): theta = atan2(||axis * sin||, cos), in degrees.

    Uses atan2 of the skew part and the trace rather than arccos((tr R - 1) / 2), which loses
    all precision near 0 deg (arccos' slope is infinite at 1): 1e-6 rad stays 1e-6 rad.
    """
    R = np.asarray(R, dtype=np.float64)
    skew = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        axis=-1,
    )
    sin = 0.5 * np.linalg.norm(skew, axis=-1)
    cos = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.degrees(np.arctan2(sin, cos))


def chordal_mean_rotation(Rs: np.ndarray) -> np.ndarray:
    """Chordal L2 mean  argmin_{Q in SO(3)} sum_i ||Q - R_i||_F^2 = proj_SO(3)(sum_i R_i).

    The projection is U diag(1, 1, det(U V^T)) V^T from the SVD of the sum. Rs: (C, 3, 3).
    """
    U, _, Vt = np.linalg.svd(np.sum(np.asarray(Rs, dtype=np.float64), axis=0))
    S = np.array([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return (U * S) @ Vt


def pose_errors(
    world_from_cam_est: np.ndarray,
    world_from_cam_ref: np.ndarray,
    remove_common_rotation: bool = False,
) -> dict:
    """Rotation and camera-centre errors after the Sim3 (ATE) alignment of camera centres.

    (s, A, b) = umeyama(c_est, c_ref) maps estimated centres into the reference frame:
    c_i' = s A c_est_i + b and R_i' = A R_est_i (world_from_cam rotations). Then
        rotation error_i = angle(R_ref_i^T R_i' Q^T),  centre error_i = ||c_i' - c_ref_i||,
    with Q = I, or with `remove_common_rotation` the chordal mean of R_ref_i^T R_i' (one
    rotation of every camera frame, e.g. from a principal point the reference refined and the
    estimate did not: every camera's optical axis then tilts by the same small angle).
    Centre errors are also given as % of the diagonal of the reference centres' bounding box.

    world_from_cam_est, world_from_cam_ref: (C, 4, 4) rigid camera-to-world (any camera-axis
    convention, but the same for both), C >= 3. Returns a dict of (C,) per-camera arrays
    (`rotation_error_deg`, `center_error`, `center_error_pct`), their medians and means, the
    alignment (`sim3_scale`, `sim3_rotation`, `sim3_translation`) and `common_rotation_deg`.
    """
    est = np.asarray(world_from_cam_est, dtype=np.float64)
    ref = np.asarray(world_from_cam_ref, dtype=np.float64)
    if est.shape != ref.shape or est.shape[-2:] != (4, 4):
        raise ValueError(f"pose_errors needs two (C, 4, 4) arrays, got {est.shape} and {ref.shape}")
    c_est, c_ref = est[:, :3, 3], ref[:, :3, 3]
    s, A, b = umeyama(c_est, c_ref)
    centers = s * c_est @ A.T + b
    R_rel = np.swapaxes(ref[:, :3, :3], -1, -2) @ (A @ est[:, :3, :3])
    Q = chordal_mean_rotation(R_rel) if remove_common_rotation else np.eye(3)
    rot_err = rotation_angle_deg(R_rel @ Q.T)
    center_err = np.linalg.norm(centers - c_ref, axis=1)
    diagonal = float(np.linalg.norm(c_ref.max(axis=0) - c_ref.min(axis=0)))
    center_pct = 100.0 * center_err / diagonal
    return {
        "num_cameras": len(est),
        "rotation_error_deg": rot_err,
        "center_error": center_err,
        "center_error_pct": center_pct,
        "median_rotation_error_deg": float(np.median(rot_err)),
        "mean_rotation_error_deg": float(np.mean(rot_err)),
        "median_center_error": float(np.median(center_err)),
        "mean_center_error": float(np.mean(center_err)),
        "median_center_error_pct": float(np.median(center_pct)),
        "mean_center_error_pct": float(np.mean(center_pct)),
        "reference_diagonal": diagonal,
        "common_rotation_deg": float(rotation_angle_deg(Q)),
        "sim3_scale": s,
        "sim3_rotation": A,
        "sim3_translation": b,
    }
