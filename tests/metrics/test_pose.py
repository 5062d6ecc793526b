"""Pose metrics: Umeyama Sim3, rotation angles, chordal mean, ATE pose errors."""

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from recon.metrics.pose import (
    chordal_mean_rotation,
    pose_errors,
    rotation_angle_deg,
    umeyama,
)


def random_rotation(rng) -> np.ndarray:
    return Rotation.random(random_state=rng).as_matrix()


def random_poses(rng, n=8) -> np.ndarray:
    """(n, 4, 4) world_from_cam with centres spread over a few units."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        poses[i, :3, :3] = random_rotation(rng)
        poses[i, :3, 3] = rng.normal(scale=3.0, size=3)
    return poses


def apply_sim3(s, R, t, world_from_cam):
    """World change x' = s R x + t applied to camera-to-world poses (rotation R, centre moved)."""
    out = world_from_cam.copy()
    out[:, :3, :3] = R @ world_from_cam[:, :3, :3]
    out[:, :3, 3] = s * world_from_cam[:, :3, 3] @ R.T + t
    return out


def test_umeyama_docstring_example():
    src = np.random.default_rng(0).normal(size=(5, 3))
    s, R, t = umeyama(src, 2 * src + [1, 0, 0])
    assert s == pytest.approx(2.0)
    np.testing.assert_allclose(R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(t, [1, 0, 0], atol=1e-12)


def test_umeyama_recovers_random_sim3_exactly():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3))
    R_true, s_true, t_true = random_rotation(rng), 0.37, rng.normal(size=3)
    dst = s_true * src @ R_true.T + t_true
    s, R, t = umeyama(src, dst)
    assert s == pytest.approx(s_true, rel=1e-12)
    np.testing.assert_allclose(R, R_true, atol=1e-12)
    np.testing.assert_allclose(t, t_true, atol=1e-12)
    # Rigid fit of a rigidly moved cloud: scale stays 1.
    s1, R1, _ = umeyama(src, src @ R_true.T + t_true, with_scale=False)
    assert s1 == 1.0
    np.testing.assert_allclose(R1, R_true, atol=1e-12)


def test_umeyama_reflection_fix_returns_a_rotation():
    """A mirrored cloud is best matched by a reflection; Umeyama must return det(R) = +1."""
    rng = np.random.default_rng(2)
    src = rng.normal(size=(30, 3)) * [3.0, 2.0, 0.5]
    dst = src * [1.0, 1.0, -1.0]
    _, R, _ = umeyama(src, dst)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_umeyama_matches_brute_force_least_squares():
    """Slow twin: generic nonlinear least squares over (log s, rotation vector, t)."""
    rng = np.random.default_rng(3)
    src = rng.normal(size=(40, 3))
    dst = (
        1.7 * src @ random_rotation(rng).T + [0.5, -1.0, 2.0] + rng.normal(scale=0.05, size=(40, 3))
    )

    def residuals(x):
        R = Rotation.from_rotvec(x[1:4]).as_matrix()
        return (np.exp(x[0]) * src @ R.T + x[4:] - dst).ravel()

    s, R, t = umeyama(src, dst)
    x0 = np.concatenate([[np.log(s)], Rotation.from_matrix(R).as_rotvec(), t])
    x0 += rng.normal(scale=0.05, size=7)  # start off the closed form
    fit = least_squares(residuals, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15)
    closed = np.concatenate([[np.log(s)], Rotation.from_matrix(R).as_rotvec(), t])
    assert np.sum(residuals(closed) ** 2) <= np.sum(fit.fun**2) + 1e-12
    np.testing.assert_allclose(fit.x, closed, atol=1e-7)


def test_rotation_angle_precise_at_small_and_large_angles():
    for angle in (1e-7, 1e-3, 0.5, 90.0, 179.9):
        R = Rotation.from_rotvec(np.radians(angle) * np.array([0.6, 0.0, 0.8])).as_matrix()
        assert rotation_angle_deg(R) == pytest.approx(angle, rel=1e-8)
    assert rotation_angle_deg(np.eye(3)) == 0.0


def test_chordal_mean_of_symmetric_pair_is_the_centre():
    rng = np.random.default_rng(4)
    Q, w = random_rotation(rng), np.radians(20.0) * np.array([0.0, 0.6, 0.8])
    Rs = np.stack(
        [Q @ Rotation.from_rotvec(w).as_matrix(), Q @ Rotation.from_rotvec(-w).as_matrix()]
    )
    np.testing.assert_allclose(chordal_mean_rotation(Rs), Q, atol=1e-12)


def test_pose_errors_zero_for_sim3_of_reference():
    rng = np.random.default_rng(5)
    ref = random_poses(rng)
    est = apply_sim3(2.5, random_rotation(rng), rng.normal(size=3), ref)
    for remove in (False, True):
        e = pose_errors(est, ref, remove_common_rotation=remove)
        assert e["median_rotation_error_deg"] < 1e-6
        assert np.max(e["center_error"]) < 1e-10
        assert e["sim3_scale"] == pytest.approx(1 / 2.5)


def test_pose_errors_one_rotated_camera():
    rng = np.random.default_rng(6)
    ref = random_poses(rng)
    est = ref.copy()
    est[3, :3, :3] = est[3, :3, :3] @ Rotation.from_rotvec([0, np.radians(2.0), 0]).as_matrix()
    e = pose_errors(est, ref)
    expected = np.zeros(len(ref))
    expected[3] = 2.0
    np.testing.assert_allclose(e["rotation_error_deg"], expected, atol=1e-9)
    np.testing.assert_allclose(e["center_error"], 0.0, atol=1e-12)


def test_pose_errors_common_rotation_removed():
    """Every camera frame turned by the same 0.5 deg (as a shifted principal point does)."""
    rng = np.random.default_rng(7)
    ref = random_poses(rng)
    Q = Rotation.from_rotvec(np.radians(0.5) * np.array([1.0, 0.0, 0.0])).as_matrix()
    est = ref.copy()
    est[:, :3, :3] = ref[:, :3, :3] @ Q
    kept = pose_errors(est, ref, remove_common_rotation=False)
    np.testing.assert_allclose(kept["rotation_error_deg"], 0.5, rtol=1e-9)
    removed = pose_errors(est, ref, remove_common_rotation=True)
    np.testing.assert_allclose(removed["rotation_error_deg"], 0.0, atol=1e-9)
    assert removed["common_rotation_deg"] == pytest.approx(0.5, rel=1e-9)


def test_pose_errors_known_centre_perturbation():
    """Octahedron centres +-e_k; the x pair stretched by (1 + e), the y pair by (1 - e).
    Worked by hand: the cross-covariance is diag(2(1+e), 2(1-e), 2) / 6, so R = I, t = 0 and
    s = 3 / (3 + 2 e^2); the errors are |s (1 + e) - 1|, |s (1 - e) - 1| and |s - 1|."""
    e = 0.1
    centres = np.concatenate([np.eye(3), -np.eye(3)])
    stretch = np.array([1 + e, 1 - e, 1.0, 1 + e, 1 - e, 1.0])
    ref = np.tile(np.eye(4), (6, 1, 1))
    ref[:, :3, 3] = centres
    est = ref.copy()
    est[:, :3, 3] = centres * stretch[:, None]
    out = pose_errors(est, ref)
    s = 3 / (3 + 2 * e**2)
    np.testing.assert_allclose(out["center_error"], np.abs(s * stretch - 1), rtol=1e-12)
    np.testing.assert_allclose(
        out["center_error_pct"], 100 * np.abs(s * stretch - 1) / (2 * np.sqrt(3))
    )
    np.testing.assert_allclose(out["rotation_error_deg"], 0.0, atol=1e-12)
    assert out["sim3_scale"] == pytest.approx(s)


def test_pose_errors_rejects_bad_shapes():
    with pytest.raises(ValueError):
        pose_errors(np.tile(np.eye(4), (4, 1, 1)), np.tile(np.eye(4), (5, 1, 1)))
