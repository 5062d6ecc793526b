"""Real spherical harmonics up to degree 3 (Sloan 2008, "Stupid
Spherical Harmonics Tricks"; as used by Yu et al. 2021 and Kerbl et al. 2023), in the ordering and sign convention of the 3DGS reference implementation so
that splat PLY files interoperate."""

from __future__ import annotations

import torch
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """(degree + 1)^2 basis functions."""
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Y_lm(d) for l <= degree. dirs: (..., 3) unit vectors -> (..., (degree+1)^2)."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """sum_k c_k Y_k(d).  coeffs: (..., K, 3) with K >= (degree+1)^2; dirs: (..., 3) -> (..., 3).

    Only the first (degree+1)^2 coefficients are used, so the degree can grow during training.
    """
    k = num_sh_bases(degree)
    basis = sh_basis(degree, dirs)  # (..., k)
    return (basis[..., :, None] * coeffs[..., :k, :]).sum(dim=-2)
