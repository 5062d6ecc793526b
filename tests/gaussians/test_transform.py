import numpy as np
import torch

from recon.cameras.conventions import rotation_from_quat_wxyz
from recon.fields.sh import eval_sh
from recon.gaussians.transform import gaussians_to_world, quat_multiply, sh_rotation_blocks


def test_sh_rotation_is_exact_for_every_degree():
    rng = np.random.default_rng(0)
    R = rotation_from_quat_wxyz(rng.normal(size=4))
    coeffs = rng.normal(size=(16, 3))
    d_world = rng.normal(size=(50, 3))
    d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
    rotated = coeffs.copy()
    for l, D in enumerate(sh_rotation_blocks(R, 3)):
        sl = slice(l * l, (l + 1) * (l + 1))
        rotated[sl] = D.T @ coeffs[sl]
    # colour seen along a world direction = colour of the scene model along R d
    a = eval_sh(3, torch.from_numpy(rotated)[None].expand(50, 16, 3), torch.from_numpy(d_world))
    b = eval_sh(
        3, torch.from_numpy(coeffs)[None].expand(50, 16, 3), torch.from_numpy(d_world @ R.T)
    )
    assert torch.allclose(a, b, atol=1e-10)


def test_gaussians_to_world_inverts_the_normalization():
    rng = np.random.default_rng(1)
    R = rotation_from_quat_wxyz(rng.normal(size=4))
    s, t = 0.25, rng.normal(size=3)
    g = {
        "means": rng.normal(size=(5, 3)),
        "quats": rng.normal(size=(5, 4)),
        "log_scales": rng.normal(size=(5, 3)),
        "opacity_logits": rng.normal(size=5),
        "sh": rng.normal(size=(5, 4, 3)),
    }
    w = gaussians_to_world(g, s, R, t)
    assert np.allclose(s * w["means"] @ R.T + t, g["means"])

    # covariance: Sigma_scene = (sR) Sigma_world (sR)^T
    def cov(q, ls):
        Rq = rotation_from_quat_wxyz(q)
        return Rq @ np.diag(np.exp(2 * ls)) @ Rq.T

    for i in range(5):
        assert np.allclose(
            s * s * R @ cov(w["quats"][i], w["log_scales"][i]) @ R.T,
            cov(g["quats"][i], g["log_scales"][i]),
        )
    assert np.allclose(quat_multiply(np.array([1.0, 0, 0, 0]), g["quats"]), g["quats"])
