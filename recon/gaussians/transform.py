"""Gaussians in the normalized scene frame -> the original (world) frame.

With x_scene = s R x_world + t: means_world = R^T (means - t) / s, log-scales - ln s,
rotations R^T q, and the SH colour re-expressed for world directions: per degree l the real
SH span is closed under rotation, Y_l(R d) = D_l Y_l(d), so c'_l = D_l^T c_l. D_l is solved by
least squares on sampled directions (exact up to float rounding; no Wigner formulas to get wrong).
"""

from __future__ import annotations

import numpy as np
import torch

from recon.cameras.conventions import quat_wxyz_from_rotation
from recon.fields.sh import sh_basis


def sh_rotation_blocks(
    R: np.ndarray, degree: int, n_dirs: int = 256, seed: int = 0
) -> list[np.ndarray]:
    """[D_0, ..., D_degree] with Y_l(R d) = D_l Y_l(d) for unit d (each (2l+1, 2l+1))."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n_dirs, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    Y = sh_basis(degree, torch.from_numpy(d)).numpy()
    YR = sh_basis(degree, torch.from_numpy(d @ R.T)).numpy()
    blocks = []
    for l in range(degree + 1):
        sl = slice(l * l, (l + 1) * (l + 1))
        Dt, *_ = np.linalg.lstsq(Y[:, sl], YR[:, sl], rcond=None)
        blocks.append(Dt.T)
    return blocks


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) wxyz quaternions."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def gaussians_to_world(
    g: dict[str, np.ndarray], scale: float, R: np.ndarray, t: np.ndarray
) -> dict:
    """g: means (G,3), quats (G,4) wxyz, log_scales (G,3), opacity_logits (G,), sh (G,K,3), all
    in the scene frame -> the same attributes in the world frame."""
    K = g["sh"].shape[1]
    degree = round(float(np.sqrt(K))) - 1
    sh = g["sh"].copy()
    for l, D in enumerate(sh_rotation_blocks(R, degree)):
        sl = slice(l * l, (l + 1) * (l + 1))
        sh[:, sl, :] = np.einsum("ij,gic->gjc", D, g["sh"][:, sl, :])  # c' = D^T c
    q_rt = quat_wxyz_from_rotation(R.T)
    quats = g["quats"] / np.maximum(np.linalg.norm(g["quats"], axis=1, keepdims=True), 1e-12)
    return {
        "means": (g["means"] - t) @ R / scale,
        "quats": quat_multiply(q_rt[None], quats),
        "log_scales": g["log_scales"] - np.log(scale),
        "opacity_logits": g["opacity_logits"],
        "sh": sh,
    }
