"""SE(3): the exponential map of a twist and its inverse, as pure batched torch functions.

A twist xi = (rho, phi) in R^6 holds a translation part rho and a rotation vector phi
(angle theta = |phi| about phi / theta). With [phi]x the skew matrix of phi (Barfoot 2017,
"State Estimation for Robotics", Sec. 7.1.4, eqs. 7.14, 7.82 and 7.86; Sola et al. 2018,
"A micro Lie theory for state estimation in robotics", eqs. 143 and 174),

    exp(xi) = [[R, V rho], [0, 1]],
    R = I + A [phi]x + B [phi]x^2,     V = I + B [phi]x + C [phi]x^2,
    A = sin(theta) / theta,  B = (1 - cos(theta)) / theta^2,  C = (theta - sin(theta)) / theta^3.

V is the left Jacobian of SO(3). A, B, C are even, entire functions of theta, evaluated from
theta^2 by their Taylor series below theta = 1 (no square root of theta^2 = 0, no 0 / 0, and
none of the cancellation in 1 - cos(theta) or theta - sin(theta) that costs a float32 closed
form three digits at theta = 1e-2) and by the closed forms above it.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

# Below this angle the coefficients come from their Taylor series in theta^2.
SERIES_BELOW = 1.0
# Terms of each series: the first one left out, theta^18 / 18!, is < 1e-16 for theta < 1.
SERIES_TERMS = 9


def skew(v: Tensor) -> Tensor:
    """[v]x with [v]x w = v x w.  (..., 3) -> (..., 3, 3); skew((0, 0, 1)) rotates x to y."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(v.shape[:-1] + (3, 3))


def _series(theta2: Tensor, offset: int) -> Tensor:
    """sum_k (-1)^k theta^2k / (2k + offset)!  by Horner in theta^2: offset 1 gives A, 2 gives
    B, 3 gives C."""
    acc = torch.zeros_like(theta2)
    for k in reversed(range(SERIES_TERMS)):
        acc = (-1) ** k / math.factorial(2 * k + offset) + theta2 * acc
    return acc


def rodrigues_coefficients(theta2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """A = sin(t)/t, B = (1 - cos t)/t^2, C = (t - sin t)/t^3 of t = sqrt(theta2).  (...,) ->
    three (...,); theta2 = 0 gives (1, 1/2, 1/6) with finite gradients (1/6 = -dA/d(theta2)).

    Both branches are evaluated on inputs made safe for them, so the one torch.where discards
    never sends inf or NaN into the gradient.
    """
    small = theta2 < SERIES_BELOW**2
    t2_series = torch.where(small, theta2, torch.zeros_like(theta2))
    t2_closed = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2_closed)
    half_sin = torch.sin(0.5 * t)
    closed = (
        torch.sin(t) / t,
        2 * half_sin * half_sin / t2_closed,  # 1 - cos t = 2 sin^2(t / 2): no cancellation
        (t - torch.sin(t)) / (t2_closed * t),
    )
    return tuple(torch.where(small, _series(t2_series, k + 1), c) for k, c in enumerate(closed))


def so3_exp(phi: Tensor) -> Tensor:
    """Rodrigues: R = I + A [phi]x + B [phi]x^2.  (..., 3) -> (..., 3, 3).
    phi = (0, 0, pi/2) gives [[0, -1, 0], [1, 0, 0], [0, 0, 1]]."""
    A, B, _ = rodrigues_coefficients((phi * phi).sum(-1))
    K = skew(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device)
    return eye + A[..., None, None] * K + B[..., None, None] * (K @ K)


def se3_exp(xi: Tensor) -> Tensor:
    """exp of twists xi = (rho, phi).  (..., 6) -> (..., 4, 4) rigid transforms [[R, V rho],
    [0, 1]]. Worked examples: (0, 0, 0, 0, 0, pi/2) is 90 deg about z with zero translation;
    (1, 2, 3, 0, 0, 0) translates by (1, 2, 3); (1, 0, 0, 0, 0, pi), half a screw turn about z,
    moves the origin to V (1, 0, 0) = (1, 0, 0) + B pi (0, 1, 0) - C pi^2 (1, 0, 0) = (0, 2/pi, 0)."""
    rho, phi = xi[..., :3], xi[..., 3:]
    A, B, C = rodrigues_coefficients((phi * phi).sum(-1))
    K = skew(phi)
    K2 = K @ K
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    R = eye + A[..., None, None] * K + B[..., None, None] * K2
    V = eye + B[..., None, None] * K + C[..., None, None] * K2
    t = (V @ rho[..., None])[..., 0]
    bottom = torch.zeros(xi.shape[:-1] + (1, 4), dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([torch.cat([R, t[..., None]], -1), bottom], -2)


def se3_adjoint(T: Tensor) -> Tensor:
    """Ad_T = [[R, [t]x R], [0, R]] for rigid (..., 4, 4) -> (..., 6, 6), twists ordered
    (rho, phi): T exp(xi) T^-1 = exp(Ad_T xi) (Barfoot 2017, Sec. 7.1.4, eq. 7.45; Sola et al.
    2018, eq. 174)."""
    R, t = T[..., :3, :3], T[..., :3, 3]
    top = torch.cat([R, skew(t) @ R], -1)
    bottom = torch.cat([torch.zeros_like(R), R], -1)
    return torch.cat([top, bottom], -2)


def so3_log(R: Tensor) -> Tensor:
    """The rotation vector phi with exp(phi) = R, |phi| in [0, pi].  (..., 3, 3) -> (..., 3).

    theta = atan2(|w|, (tr R - 1) / 2) with w = vee(R - R^T) / 2 = sin(theta) a, so small angles
    keep full precision (arccos would not). Then phi = theta a, with a = w / |w| unless theta is
    within 1e-3 of pi, where w vanishes: there a is the largest column of
    (R + R^T) / 2 - cos(theta) I = (1 - cos(theta)) a a^T, signed to agree with w.
    """
    w = 0.5 * torch.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )
    sin = w.norm(dim=-1)
    cos = 0.5 * (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1)
    theta = torch.atan2(sin, cos)
    # theta / sin(theta) = 1 + theta^2 / 6 + ... near 0 (A's reciprocal)
    ratio = 1.0 / rodrigues_coefficients(theta * theta)[0]
    phi = ratio[..., None] * w
    near_pi = theta > math.pi - 1e-3
    if bool(near_pi.any()):
        eye = torch.eye(3, dtype=R.dtype, device=R.device)
        S = 0.5 * (R + R.transpose(-1, -2)) - cos[..., None, None] * eye
        col = S.diagonal(dim1=-2, dim2=-1).argmax(-1)
        a = torch.take_along_dim(S, col[..., None, None].expand(S.shape[:-2] + (3, 1)), -1)[..., 0]
        a = a / a.norm(dim=-1, keepdim=True)
        a = torch.where((a * w).sum(-1, keepdim=True) < 0, -a, a)
        phi = torch.where(near_pi[..., None], theta[..., None] * a, phi)
    return phi


def se3_log(T: Tensor) -> Tensor:
    """The twist xi = (rho, phi) with exp(xi) = T for rigid (..., 4, 4) -> (..., 6), rotation
    angle in [0, pi]; rho solves V rho = t (V is invertible for theta < 2 pi)."""
    phi = so3_log(T[..., :3, :3])
    _, B, C = rodrigues_coefficients((phi * phi).sum(-1))
    K = skew(phi)
    eye = torch.eye(3, dtype=T.dtype, device=T.device)
    V = eye + B[..., None, None] * K + C[..., None, None] * (K @ K)
    rho = torch.linalg.solve(V, T[..., :3, 3:])[..., 0]
    return torch.cat([rho, phi], -1)
