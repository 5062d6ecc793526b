"""SE(3) exp / log: worked examples, round trips, the Taylor branch against 50-digit closed forms,
finite and exact gradients at and near theta = 0, float64 gradcheck."""

import math

import mpmath
import pytest
import torch

from recon.cameras.se3 import (
    rodrigues_coefficients,
    se3_adjoint,
    se3_exp,
    se3_log,
    skew,
    so3_exp,
    so3_log,
)

F64 = torch.float64


def exact_coefficients(theta: float) -> tuple[float, float, float]:
    """A, B, C of the closed forms in 50-digit arithmetic (no cancellation left)."""
    with mpmath.workdps(50):
        t = mpmath.mpf(theta)
        if t == 0:
            return 1.0, 0.5, 1 / 6
        return (
            float(mpmath.sin(t) / t),
            float((1 - mpmath.cos(t)) / t**2),
            float((t - mpmath.sin(t)) / t**3),
        )


def test_rotation_by_90_degrees_about_z():
    T = se3_exp(torch.tensor([0.0, 0, 0, 0, 0, math.pi / 2], dtype=F64))
    expected = torch.tensor([[0.0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=F64)
    assert torch.allclose(T, expected, atol=1e-15)
    assert torch.allclose(
        T[:3, :3] @ torch.tensor([1.0, 0, 0], dtype=F64),
        torch.tensor([0.0, 1, 0], dtype=F64),
        atol=1e-15,
    )


def test_pure_translation_and_half_screw():
    T = se3_exp(torch.tensor([1.0, 2, 3, 0, 0, 0], dtype=F64))
    expected = torch.eye(4, dtype=F64)
    expected[:3, 3] = torch.tensor([1.0, 2, 3])
    assert torch.equal(T, expected)
    # half a screw turn about z: V (1, 0, 0) = (0, 2 / pi, 0)
    T = se3_exp(torch.tensor([1.0, 0, 0, 0, 0, math.pi], dtype=F64))
    assert torch.allclose(T[:3, 3], torch.tensor([0.0, 2 / math.pi, 0], dtype=F64), atol=1e-15)


@pytest.mark.parametrize("theta", [0.0, 1e-8, 1e-4, 1e-2, 0.3, 0.999999, 1.0, 1.000001, 2.0, 3.1])
def test_coefficients_match_the_closed_forms_to_float64_precision(theta):
    got = rodrigues_coefficients(torch.tensor(theta * theta, dtype=F64))
    for value, exact in zip(got, exact_coefficients(theta)):
        assert abs(float(value) - exact) <= 2e-16 * abs(exact), (theta, float(value), exact)


@pytest.mark.parametrize("theta", [1e-3, 1e-2, 0.1, 0.5, 0.99, 1.5])
def test_float32_coefficients_keep_float32_precision(theta):
    """The series / the half-angle form avoid the cancellation of 1 - cos and t - sin."""
    got = rodrigues_coefficients(torch.tensor(theta * theta, dtype=torch.float32))
    for value, exact in zip(got, exact_coefficients(theta)):
        assert abs(float(value) - exact) <= 4e-7 * abs(exact), (theta, float(value), exact)


def test_coefficient_derivatives_are_continuous_at_the_branch_switch():
    """d/d(theta^2) of A, B, C just below and just above theta = 1 agree (and with mpmath)."""
    grads = []
    for theta in (1 - 1e-9, 1 + 1e-9):
        t2 = torch.tensor(theta * theta, dtype=F64, requires_grad=True)
        grads.append(
            torch.stack(
                [
                    torch.autograd.grad(c, t2, retain_graph=True)[0]
                    for c in rodrigues_coefficients(t2)
                ]
            )
        )
    assert torch.allclose(grads[0], grads[1], rtol=1e-8, atol=0)
    with mpmath.workdps(50):
        dA = mpmath.diff(lambda s: mpmath.sin(mpmath.sqrt(s)) / mpmath.sqrt(s), 1)
    assert abs(float(grads[0][0]) - float(dA)) < 1e-8


@pytest.mark.parametrize("theta", [0.0, 1e-8, 1e-4])
def test_exp_is_exact_and_its_jacobian_finite_near_zero(theta):
    axis = torch.tensor([0.36, -0.48, 0.8], dtype=F64)
    rho = torch.tensor([0.3, -0.2, 0.5], dtype=F64)
    xi = torch.cat([rho, theta * axis])
    T = se3_exp(xi)
    A, B, C = exact_coefficients(theta)
    K = skew(theta * axis)
    R = torch.eye(3, dtype=F64) + A * K + B * (K @ K)
    t = (torch.eye(3, dtype=F64) + B * K + C * (K @ K)) @ rho
    assert torch.allclose(T[:3, :3], R, rtol=0, atol=2e-16)
    assert torch.allclose(T[:3, 3], t, rtol=0, atol=2e-16)
    J = torch.autograd.functional.jacobian(se3_exp, xi)  # (4, 4, 6)
    assert torch.isfinite(J).all()
    if theta == 0.0:  # the generators: dR/dphi_k = [e_k]x, dt/drho = I, dt/dphi = -[rho]x / 2
        for k in range(3):
            assert torch.equal(J[:3, :3, 3 + k], skew(torch.eye(3, dtype=F64)[k]))
        assert torch.equal(J[:3, 3, :3], torch.eye(3, dtype=F64))
        assert torch.allclose(J[:3, 3, 3:], -0.5 * skew(rho), atol=1e-16)
        assert not J[3].any()


def random_twists(n, seed, max_angle=3.0):
    gen = torch.Generator().manual_seed(seed)
    rho = torch.randn(n, 3, generator=gen, dtype=F64)
    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=F64), dim=-1)
    angle = torch.rand(n, 1, generator=gen, dtype=F64) * max_angle
    angle[:4, 0] = torch.tensor([0.0, 1e-9, 1e-5, 0.9999], dtype=F64)
    return torch.cat([rho, angle * axis], -1)


def test_exp_gives_rigid_transforms_and_log_inverts_it():
    xi = random_twists(64, seed=0)
    T = se3_exp(xi)
    R = T[:, :3, :3]
    assert torch.allclose(
        R @ R.transpose(1, 2), torch.eye(3, dtype=F64).expand(64, 3, 3), atol=1e-14
    )
    assert torch.allclose(torch.linalg.det(R), torch.ones(64, dtype=F64), atol=1e-14)
    assert torch.equal(T[:, 3], torch.tensor([0.0, 0, 0, 1], dtype=F64).expand(64, 4))
    assert torch.allclose(se3_log(T), xi, rtol=1e-10, atol=1e-12)
    assert torch.allclose(se3_exp(se3_log(T)), T, atol=1e-13)


def test_log_of_rotations_near_pi():
    """At theta -> pi the skew part vanishes; the axis comes from the symmetric part."""
    axis = torch.nn.functional.normalize(
        torch.tensor([[0.2, -0.7, 0.4], [-1.0, 0.1, 0.05]], dtype=F64), dim=-1
    )
    for angle in (math.pi, math.pi - 1e-7, math.pi - 1e-4):
        R = so3_exp(angle * axis)
        phi = so3_log(R)
        assert torch.allclose(so3_exp(phi), R, atol=1e-12), angle
        assert torch.allclose(phi.norm(dim=-1), torch.full((2,), angle, dtype=F64), atol=1e-9)


def test_exp_gradcheck_float64():
    xi = random_twists(6, seed=1).requires_grad_()
    assert torch.autograd.gradcheck(se3_exp, (xi,), eps=1e-6, atol=1e-8)
    small = torch.cat([torch.randn(3, 3, dtype=F64), 1e-7 * torch.randn(3, 3, dtype=F64)], -1)
    assert torch.autograd.gradcheck(se3_exp, (small.requires_grad_(),), eps=1e-6, atol=1e-8)
    assert torch.autograd.gradgradcheck(se3_exp, (xi,), eps=1e-6, atol=1e-6)


def test_adjoint_moves_a_twist_between_frames():
    """T exp(xi) T^-1 = exp(Ad_T xi), and Ad of a product is the product of the Ads."""
    T, U = random_twists(8, seed=4)[6:].unbind(0)
    T, U = se3_exp(T), se3_exp(U)
    xi = random_twists(5, seed=5)
    lhs = T @ se3_exp(xi) @ torch.linalg.inv(T)
    assert torch.allclose(lhs, se3_exp(xi @ se3_adjoint(T).T), atol=1e-12)
    assert torch.allclose(se3_adjoint(T @ U), se3_adjoint(T) @ se3_adjoint(U), atol=1e-12)
