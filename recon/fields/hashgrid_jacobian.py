"""The multiresolution hash encoding's Jacobian in the position, J = d(enc)/dx (N, L F, 3), for
a field's analytic gradient (a signed distance field's normal and eikonal term).

Level l interpolates its cell's 8 corner features with trilinear weights w_c, each a product of
one factor per axis (f or 1 - f, with f the fraction of x N_l in the cell), so

    d w_c / d x_a = N_l (+-1) x (the other two axes' factors),
    J[l F + k, a] = sum_c table[row_c, k] d w_c / d x_a,

linear in the table (so differentiable in it), and 0 outside (0, 1)^3, where the encoding clamps
x. A field that needs both the encoding and J at the same points (an SDF's training forward)
gets them from one pass over the corners (`hash_encode_and_jacobian`), and the table's gradient
of both from one scatter:

    d loss / d table[row_c, k] += w_c g_enc[l F + k] + sum_a (d w_c / d x_a) g_jac[l F + k, a].

The numba kernels run on CPU; `hash_jacobian_torch` with `hash_encode_torch` is the twin used
elsewhere (its level constants resident on the device: `hashgrid.level_tensors`) and in the
tests.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from recon import devices
from recon.fields.hashgrid import (
    _cell,
    _fill_corners,
    _layout_arrays,
    _level,
    corner_indices_and_weights,
    gather_rows,
    hash_encode_torch,
    level_tensors,
)


@numba.njit(cache=True, inline="always")
def _fill_slopes(x, p, n, nf, inside, dws):  # pragma: no cover
    """dws[c, a] = d w_c / d x_a for the 8 corners c = dx + 2 dy + 4 dz of point p's cell on
    one level (0 everywhere when the point lies outside (0, 1)^3)."""
    _, fx = _cell(x[p, 0], nf, n)
    _, fy = _cell(x[p, 1], nf, n)
    _, fz = _cell(x[p, 2], nf, n)
    c = 0
    for dz in range(2):
        wz = fz if dz else 1 - fz
        sz = nf if dz else -nf
        for dy in range(2):
            wy = fy if dy else 1 - fy
            sy = nf if dy else -nf
            for dx in range(2):
                wx = fx if dx else 1 - fx
                sx = nf if dx else -nf
                if inside:
                    dws[c, 0] = sx * wy * wz
                    dws[c, 1] = wx * sy * wz
                    dws[c, 2] = wx * wy * sz
                else:
                    dws[c, 0] = dws[c, 1] = dws[c, 2] = 0.0
                c += 1


@numba.njit(parallel=True, cache=True)
def _encode_jacobian_kernel(
    x, inside, table, enc, jac, res, resf, size, dense, offset, backward
):  # pragma: no cover
    """forward:  enc[p, l F + k] = sum_c w_c table[row_c, k],
              jac[p, l F + k, a] = sum_c dw_c/dx_a table[row_c, k];
    backward: table[row_c, k] += w_c enc[p, l F + k] + sum_a dw_c/dx_a jac[p, l F + k, a]
              (table the gradient buffer, enc and jac the outputs' gradients: one scatter).
    x (N, 3) clamped to [0, 1]; inside (N,) bool. Parallel over levels, each thread streaming
    every point through its levels' slices of the table: no other thread writes a level's
    rows, so the scatter has no races."""
    n_pts, n_levels, n_feat = x.shape[0], res.shape[0], table.shape[1]
    for lv in numba.prange(n_levels):
        n, nf, sz, off, dn, stride_y, stride_z, pow2 = _level(res, resf, size, dense, offset, lv)
        rows = np.empty(8, np.int64)
        ws = np.empty(8, x.dtype)
        dws = np.empty((8, 3), x.dtype)
        for p in range(n_pts):
            _fill_corners(x, p, n, nf, dn, sz, pow2, stride_y, stride_z, off, rows, ws)
            _fill_slopes(x, p, n, nf, inside[p], dws)
            for k in range(n_feat):
                col = lv * n_feat + k
                if backward:
                    ge, ga0, ga1, ga2 = enc[p, col], jac[p, col, 0], jac[p, col, 1], jac[p, col, 2]
                    for c in range(8):
                        table[rows[c], k] += (
                            ws[c] * ge + dws[c, 0] * ga0 + dws[c, 1] * ga1 + dws[c, 2] * ga2
                        )
                else:
                    e = j0 = j1 = j2 = 0.0
                    for c in range(8):
                        v = table[rows[c], k]
                        e += ws[c] * v
                        j0 += dws[c, 0] * v
                        j1 += dws[c, 1] * v
                        j2 += dws[c, 2] * v
                    enc[p, col] = e
                    jac[p, col, 0] = j0
                    jac[p, col, 1] = j1
                    jac[p, col, 2] = j2


def _kernel_args(x: Tensor, layout: dict) -> tuple:
    """(clamped x, inside, res, resf, size, dense, offset) as the kernels take them."""
    res, size, offset, dense = _layout_arrays(layout)
    xs = x.detach().clamp(0.0, 1.0).contiguous()
    inside = ((x > 0) & (x < 1)).all(-1).contiguous()
    return xs, inside, res, res.astype(xs.numpy().dtype), size, dense, offset


class _HashEncodeJacobianCPU(torch.autograd.Function):
    """(encoding (N, L F), Jacobian (N, L F, 3)) by numba in one pass; differentiable in the
    table (both are linear in it), not in x (sample points are data)."""

    @staticmethod
    def forward(ctx, x: Tensor, table: Tensor, layout: dict) -> tuple[Tensor, Tensor]:
        xs, inside, res, resf, size, dense, offset = _kernel_args(x, layout)
        out_dim = len(res) * table.shape[1]
        enc = torch.empty((x.shape[0], out_dim), dtype=table.dtype)
        jac = torch.empty((x.shape[0], out_dim, 3), dtype=table.dtype)
        tab = table.detach().contiguous().numpy()
        _encode_jacobian_kernel(
            xs.numpy(), inside.numpy(), tab, enc.numpy(), jac.numpy(),
            res, resf, size, dense, offset, False,
        )  # fmt: skip
        ctx.save_for_backward(xs, inside)
        ctx.layout, ctx.table_shape = layout, table.shape
        return enc, jac

    @staticmethod
    def backward(ctx, grad_enc: Tensor, grad_jac: Tensor):
        xs, inside = ctx.saved_tensors
        res, size, offset, dense = _layout_arrays(ctx.layout)
        resf = res.astype(xs.numpy().dtype)
        grad_table = torch.zeros(ctx.table_shape, dtype=grad_jac.dtype)
        _encode_jacobian_kernel(
            xs.numpy(), inside.numpy(), grad_table.numpy(),
            grad_enc.detach().contiguous().numpy(), grad_jac.detach().contiguous().numpy(),
            res, resf, size, dense, offset, True,
        )  # fmt: skip
        return None, grad_table, None


def hash_jacobian_torch(x: Tensor, table: Tensor, layout: dict[str, list[int]]) -> Tensor:
    """d(encoding)/dx (N, L F, 3) in pure torch (any device; the twin of the numba kernel):
    sum_c table[row_c] dw_c/dx_a, with dw_c/dx_a = N_l (+-1) x the other two axes' factors;
    0 outside (0, 1)^3, where the encoding clamps x."""
    idx, _ = corner_indices_and_weights(x, layout)  # (N, L, 8)
    lv = level_tensors(layout, x.device)
    res, bits = lv.resolution.to(x.dtype), lv.bits
    pos = x.clamp(0.0, 1.0)[:, None, :] * res[None, :, None]  # (N, L, 3)
    i0 = torch.minimum(pos.floor(), (res - 1)[None, :, None])
    frac = pos - i0
    factor = torch.where(bits.bool(), frac[:, :, None, :], 1.0 - frac[:, :, None, :])  # N,L,8,3
    slope = torch.where(bits.bool(), 1.0, -1.0).to(x.dtype) * res[None, :, None, None]
    dw = torch.stack(
        [
            slope[..., 0] * factor[..., 1] * factor[..., 2],
            factor[..., 0] * slope[..., 1] * factor[..., 2],
            factor[..., 0] * factor[..., 1] * slope[..., 2],
        ],
        -1,
    )  # (N, L, 8, 3)
    inside = ((x > 0) & (x < 1)).all(-1).to(x.dtype)[:, None, None, None]
    jac = torch.einsum("nlcf,nlca->nlfa", gather_rows(table, idx), dw * inside)
    return jac.flatten(1, 2)


def hash_encode_and_jacobian(
    x: Tensor, table: Tensor, layout: dict[str, list[int]]
) -> tuple[Tensor, Tensor]:
    """(encoding (N, L F), d(encoding)/dx (N, L F, 3)) at x (N, 3), both differentiable in the
    table and not in x: one numba pass on CPU, the torch twins elsewhere."""
    if devices.uses_cpu_kernels(x) and x.dtype == table.dtype:
        return _HashEncodeJacobianCPU.apply(x, table, layout)
    return hash_encode_torch(x.detach(), table, layout), hash_jacobian_torch(x, table, layout)
