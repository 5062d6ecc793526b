"""The spherical-harmonic basis of one direction inside numba kernels: the twin of
`sh.sh_basis` (same ordering, signs and constants), checked against it in tests/fields/test_sh.py."""

from __future__ import annotations

import numba

from recon.fields.sh import C0, C1, C2, C3


@numba.njit(cache=True, inline="always")
def sh_basis_at(degree, x, y, z, out):
    """Y_k(d) for k < (degree + 1)^2 (degree <= 3) of the unit direction d = (x, y, z), written
    to out[:k]."""
    out[0] = C0
    if degree >= 1:
        out[1] = -C1 * y
        out[2] = C1 * z
        out[3] = -C1 * x
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out[4] = C2[0] * xy
        out[5] = C2[1] * yz
        out[6] = C2[2] * (2.0 * zz - xx - yy)
        out[7] = C2[3] * xz
        out[8] = C2[4] * (xx - yy)
        if degree >= 3:
            out[9] = C3[0] * y * (3.0 * xx - yy)
            out[10] = C3[1] * xy * z
            out[11] = C3[2] * y * (4.0 * zz - xx - yy)
            out[12] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
            out[13] = C3[4] * x * (4.0 * zz - xx - yy)
            out[14] = C3[5] * z * (xx - yy)
            out[15] = C3[6] * x * (xx - 3.0 * yy)
