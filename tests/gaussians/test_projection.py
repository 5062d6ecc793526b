"""Quaternion -> R, Sigma = R S S^T R^T, EWA projection, the stable conic, the 3-sigma radius
and SH colour: a worked example, brute-force twins and hard cases."""

import math

import numpy as np
import pytest
import torch

from recon.cameras.conventions import rotation_from_quat_wxyz
from recon.fields.sh import C0
from recon.gaussians.projection import (
    DILATION,
    antialias_compensation,
    conic_from_cov2d,
    covariance_3d,
    covariance_factor,
    ewa_covariance_2d,
    project_gaussians,
    radius_3sigma,
    rotation_from_quats,
    sh_colors,
)

F64 = torch.float64


def problem5():
    """A worked EWA example (Zwicker et al. 2001; Kerbl et al. 2023, eq. 5): camera-space mean (0.4, -0.2, 2), scales (0.1, 0.05, 0.2), 30 deg about
    z, fx = fy = 1111; a 2000 x 2000 image centred on the axis so the guard band is inactive."""
    half = math.radians(30.0) / 2
    quat = torch.tensor([[math.cos(half), 0.0, 0.0, math.sin(half)]], dtype=F64)
    log_scales = torch.log(torch.tensor([[0.10, 0.05, 0.20]], dtype=F64))
    mean = torch.tensor([[0.4, -0.2, 2.0]], dtype=F64)
    K = torch.tensor([[1111.0, 0, 1000], [0, 1111.0, 1000], [0, 0, 1]], dtype=F64)
    return mean, quat, log_scales, K


def test_problem5_covariances_eigenvalues_and_weight():
    mean, quat, log_scales, K = problem5()
    Sigma = covariance_3d(quat, log_scales)[0]
    expected = torch.tensor([[0.00813, 0.00325, 0], [0.00325, 0.00438, 0], [0, 0, 0.04]], dtype=F64)
    assert torch.allclose(Sigma, expected, atol=1e-5)
    cov2d = ewa_covariance_2d(mean, covariance_factor(quat, log_scales), K, 2000, 2000)[0]
    a, b, c = cov2d.tolist()
    assert (a - 0.3, b, c - 0.3) == pytest.approx((3000.94, 755.28, 1473.47), abs=0.01)
    eig = torch.linalg.eigvalsh(torch.tensor([[a, b], [b, c]], dtype=F64))
    assert eig.tolist() == pytest.approx([1163.4, 3311.6], abs=0.05)
    conic, valid = conic_from_cov2d(cov2d[None])
    assert bool(valid[0])
    A, B, C = conic[0].tolist()
    assert (A, B, C) == pytest.approx((3.83e-4, -1.96e-4, 7.79e-4), abs=0.006e-4)
    dx, dy = 2.0, 1.0
    assert math.exp(-0.5 * (A * dx * dx + 2 * B * dx * dy + C * dy * dy)) == pytest.approx(
        0.99924, abs=5e-6
    )


def test_problem5_through_project_gaussians():
    mean, quat, log_scales, K = problem5()
    means2d, _conics, depths, radii = project_gaussians(
        mean, quat, log_scales, K, torch.eye(4, dtype=F64), 2000, 2000
    )
    assert means2d[0].tolist() == pytest.approx([1111 * 0.2 + 1000, -1111 * 0.1 + 1000])
    assert float(depths[0]) == 2.0
    assert float(radii[0]) == math.ceil(
        3 * math.sqrt(3311.6)
    )  # 173 px: 3 sigma of the larger eigenvalue


def test_covariance_is_the_product_of_its_factor():
    q, log_s = torch.randn(5, 4, dtype=F64), torch.randn(5, 3, dtype=F64)
    M = covariance_factor(q, log_s)
    assert torch.allclose(covariance_3d(q, log_s), M @ M.transpose(-1, -2))


def test_rotation_matches_colmap_convention_and_is_orthonormal():
    q = torch.randn(50, 4, dtype=F64)
    R = rotation_from_quats(q)
    assert np.allclose(R.numpy(), rotation_from_quat_wxyz(q.numpy()), atol=1e-12)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=F64).expand(50, 3, 3))
    assert torch.allclose(torch.linalg.det(R), torch.ones(50, dtype=F64))


def test_zero_quaternion_is_identity_without_nan():
    q = torch.zeros(1, 4, dtype=F64, requires_grad=True)
    R = rotation_from_quats(q)
    assert torch.equal(R[0], torch.eye(3, dtype=F64))
    cov = covariance_3d(q, torch.zeros(1, 3, dtype=F64))
    (g,) = torch.autograd.grad(cov.sum() + R.sum(), q)
    assert torch.isfinite(g).all()


@pytest.mark.parametrize("scale", [1e-8, 1e3])
def test_covariance_extreme_scales(scale):
    q = torch.randn(8, 4, dtype=F64, requires_grad=True)
    log_s = torch.full((8, 3), math.log(scale), dtype=F64, requires_grad=True)
    cov = covariance_3d(q, log_s)
    # Isotropic: R S S^T R^T = s^2 I whatever R is.
    eye = torch.eye(3, dtype=F64).expand(8, 3, 3)
    assert torch.allclose(cov / scale**2, eye, rtol=1e-12, atol=1e-12)
    grads = torch.autograd.grad(cov.sum(), [q, log_s])
    assert all(torch.isfinite(g).all() for g in grads)


def test_ewa_matches_autograd_jacobian_of_the_projection():
    torch.manual_seed(0)
    K = torch.tensor([[300.0, 0, 160], [0, 280.0, 120], [0, 0, 1]], dtype=F64)
    points = torch.randn(6, 3, dtype=F64) * 0.3 + torch.tensor([0, 0, 3.0], dtype=F64)
    L = torch.randn(6, 3, 3, dtype=F64) * 0.1
    Sigma = L @ L.transpose(-1, -2)
    cov2d = ewa_covariance_2d(points, L, K, 320, 240)

    def pixel(p):
        return torch.stack([K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2]])

    for i in range(6):
        J = torch.autograd.functional.jacobian(pixel, points[i])
        ref = J @ Sigma[i] @ J.T + 0.3 * torch.eye(2, dtype=F64)
        assert torch.allclose(cov2d[i], torch.stack([ref[0, 0], ref[0, 1], ref[1, 1]]))


def test_guard_band_clamps_x_over_z_to_1_3_times_the_frustum():
    K = torch.tensor([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]], dtype=F64)
    Sigma = torch.diag(torch.tensor([0.1, 0.2, 0.3], dtype=F64))[None]  # a factor of the cov
    far_out = torch.tensor([[10.0, 0.0, 2.0]], dtype=F64)  # x/z = 5, the limit is 0.5 * 1.3
    on_edge = torch.tensor([[0.65 * 2.0, 0.0, 2.0]], dtype=F64)
    assert torch.allclose(
        ewa_covariance_2d(far_out, Sigma, K, 100, 100),
        ewa_covariance_2d(on_edge, Sigma, K, 100, 100),
    )


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("scale", [1e-20, 1e-6, 1.0, 1e6, 1e20])
def test_conic_is_stable_for_tiny_and_huge_determinants(dtype, scale):
    """det = scale^2 spans 1e-40 .. 1e40 (beyond float32's range when formed naively)."""
    torch.manual_seed(1)
    L = torch.randn(16, 2, 2, dtype=F64)
    cov = (L @ L.transpose(-1, -2) + 0.1 * torch.eye(2, dtype=F64)) * scale
    packed = torch.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]], -1).to(dtype)
    conic, valid = conic_from_cov2d(packed)
    assert valid.all() and torch.isfinite(conic).all()
    inv = torch.linalg.inv(cov)
    expected = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
    tol = 1e-4 if dtype == torch.float32 else 1e-10
    assert torch.allclose(conic.double() / (1 / scale), expected / (1 / scale), rtol=tol, atol=tol)


def test_conic_of_a_degenerate_covariance_is_invalid_and_finite():
    packed = torch.tensor(
        [[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 1.0], [float("inf"), 0.0, 1.0]],
        requires_grad=True,
    )
    conic, valid = conic_from_cov2d(packed)
    assert not valid.any() and torch.equal(conic, torch.zeros_like(conic))
    (g,) = torch.autograd.grad(conic.sum(), packed)
    assert torch.isfinite(g).all()


def test_radius_is_three_sigma_of_the_larger_eigenvalue():
    torch.manual_seed(2)
    L = torch.randn(64, 2, 2, dtype=F64) * 5
    cov = L @ L.transpose(-1, -2) + 0.3 * torch.eye(2, dtype=F64)
    packed = torch.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]], -1)
    lam = torch.linalg.eigvalsh(cov)
    separated = (lam[:, 1] - lam[:, 0]) > 2 * 0.1**0.5  # away from the reference's 0.1 floor
    expected = torch.ceil(3 * torch.sqrt(lam[:, 1]))
    assert torch.equal(radius_3sigma(packed)[separated], expected[separated])


def camera_setup():
    K = torch.tensor([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]], dtype=F64)
    return K, torch.eye(4, dtype=F64)


@pytest.mark.parametrize("z, culled", [(0.0, True), (-1.0, True), (0.005, True), (0.05, False)])
def test_camera_plane_behind_and_straddling_near_plane(z, culled):
    """On the camera plane, behind the camera and inside the near plane: culled; a centre just
    beyond the near plane with a 0.2 scale straddles it: kept. Gradients finite in all cases."""
    K, cfw = camera_setup()
    means = torch.tensor([[0.0, 0.0, z]], dtype=F64, requires_grad=True)
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=F64, requires_grad=True)
    log_s = torch.log(torch.tensor([[0.2, 0.2, 0.2]], dtype=F64)).requires_grad_()
    means2d, conics, depths, radii = project_gaussians(means, quats, log_s, K, cfw, 64, 64)
    assert (float(radii[0]) == 0) == culled
    out = means2d.sum() + conics.sum() + depths.sum()
    assert all(torch.isfinite(t).all() for t in (means2d, conics, depths))
    grads = torch.autograd.grad(out, [means, quats, log_s])
    assert all(torch.isfinite(g).all() for g in grads)


@pytest.mark.parametrize(
    "scale, radius", [(1e-8, math.ceil(3 * math.sqrt(0.3 + 0.1**0.5))), (1e3, None)]
)
def test_tiny_and_huge_scales_project_finitely(scale, radius):
    K, cfw = camera_setup()
    means = torch.tensor([[0.1, 0.0, 2.0]], dtype=F64, requires_grad=True)
    quats = torch.tensor([[0.9, 0.1, 0.2, 0.3]], dtype=F64, requires_grad=True)
    log_s = torch.full((1, 3), math.log(scale), dtype=F64, requires_grad=True)
    means2d, conics, _depths, radii = project_gaussians(means, quats, log_s, K, cfw, 64, 64)
    if radius is not None:  # the 0.3 px dilation alone: a one-pixel splat
        assert float(radii[0]) == radius
    else:  # covers the whole image
        assert float(radii[0]) > 1e4
    grads = torch.autograd.grad(means2d.sum() + conics.sum(), [means, quats, log_s])
    assert all(torch.isfinite(g).all() for g in grads)


def test_outside_the_image_is_culled():
    K, cfw = camera_setup()
    means = torch.tensor([[5.0, 0.0, 1.0], [0.0, 0.0, 1.0]], dtype=F64)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=F64)
    log_s = torch.full((2, 3), math.log(0.01), dtype=F64)
    radii = project_gaussians(means, quats, log_s, K, cfw, 64, 64)[3]
    assert float(radii[0]) == 0 and float(radii[1]) > 0


def test_sh_colour_is_offset_by_half_and_clamped_at_zero():
    means = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=F64)
    sh = torch.zeros(2, 16, 3, dtype=F64)
    sh[0, 0] = torch.tensor([1.0, -1.0, 0.0], dtype=F64)
    sh[1, 0] = torch.tensor([-10.0, 0.0, 0.0], dtype=F64)
    sh = sh.requires_grad_()
    colors = sh_colors(means, sh, 3, torch.zeros(3, dtype=F64))
    assert colors[0].tolist() == pytest.approx([C0 + 0.5, -C0 + 0.5, 0.5])
    assert colors[1].tolist() == [0.0, 0.5, 0.5]
    (g,) = torch.autograd.grad(colors.sum(), sh)
    assert g[1, 0, 0] == 0  # the clamp passes no gradient


def test_antialias_compensation_worked_example_and_limits():
    """Sigma = diag(0.3, 1.2) -> Sigma' = diag(0.6, 1.5), sqrt(0.36 / 0.9) = 0.63246; a splat
    much larger than the dilation keeps its opacity, a point-like one loses it."""
    conics = torch.tensor([[1 / 0.6, 0.0, 1 / 1.5], [1 / 1e4, 0, 1 / 1e4], [1 / 0.3, 0, 1 / 0.3]])
    rho = antialias_compensation(conics.double())
    assert rho[0].item() == pytest.approx(0.632456, abs=1e-6)
    assert rho[1].item() == pytest.approx(1.0, abs=1e-4)
    assert rho[2].item() < 1e-5


def test_antialias_compensation_keeps_the_undilated_integral():
    """Brute force: over a fine grid, rho exp(-x^T Sigma'^-1 x / 2) integrates to the
    undilated 2 pi sqrt(det Sigma), for random anisotropic covariances."""
    gen = torch.Generator().manual_seed(3)
    for _ in range(4):
        L = torch.randn(2, 2, generator=gen, dtype=F64) * 0.8
        cov = L @ L.T + 0.02 * torch.eye(2, dtype=F64)
        dilated = cov + DILATION * torch.eye(2, dtype=F64)
        conic_m = torch.linalg.inv(dilated)
        conic = torch.stack([conic_m[0, 0], conic_m[0, 1], conic_m[1, 1]])
        rho = antialias_compensation(conic[None])[0]
        x = torch.linspace(-15, 15, 1501, dtype=F64)
        X, Y = torch.meshgrid(x, x, indexing="xy")
        power = conic[0] * X * X + 2 * conic[1] * X * Y + conic[2] * Y * Y
        integral = (rho * torch.exp(-0.5 * power)).sum() * (x[1] - x[0]) ** 2
        expected = 2 * math.pi * torch.sqrt(torch.linalg.det(cov))
        assert integral.item() == pytest.approx(expected.item(), rel=1e-6)


def test_antialias_compensation_gradient():
    conics = torch.tensor([[1.2, 0.3, 0.9], [0.5, -0.1, 2.0]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(antialias_compensation, (conics,))
