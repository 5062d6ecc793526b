"""Fast CPU path for the sparse voxel grid's trilinear lookup (numba), with a custom backward.

The slow, obviously-correct twin is `SparseVoxelGrid.query_reference` (torch gather + autograd);
`tests/models/test_plenoxel.py` compares both on values and gradients.

Forward:  out[n] = sum_c w[n, c] * data[rows[n, c]]          (rows < 0 contribute nothing)
Backward: grad_data[rows[n, c]] += w[n, c] * grad_out[n]       (serial scatter: no atomics,
          deterministic order, and cheap next to the gather for the sizes a CPU step uses)
"""

from __future__ import annotations

import numba
import torch
from torch import Tensor

from recon import devices


@numba.njit(cache=True, inline="always")
def lattice_cell(x0, x1, x2, res):
    """`voxels.trilinear_corners` for one point: the lower vertex (i0, i1, i2) of its cell and
    the fractions (f0, f1, f2), x clamped to [0, 1]."""
    g0 = min(max(x0, 0.0), 1.0) * (res - 1)
    g1 = min(max(x1, 0.0), 1.0) * (res - 1)
    g2 = min(max(x2, 0.0), 1.0) * (res - 1)
    i0 = min(int(g0), res - 2)
    i1 = min(int(g1), res - 2)
    i2 = min(int(g2), res - 2)
    return i0, i1, i2, g0 - i0, g1 - i1, g2 - i2


@numba.njit(cache=True, inline="always")
def lattice_cell_index(x0, x1, x2, res):
    """Flat index i0 + i1 (res - 1) + i2 (res - 1)^2 of the lattice cell holding a unit-cube point."""
    i0, i1, i2, _, _, _ = lattice_cell(x0, x1, x2, res)
    return i0 + (res - 1) * (i1 + (res - 1) * i2)


@numba.njit(cache=True, inline="always")
def lattice_value(x0, x1, x2, res, links, values):
    """The trilinear value at one unit-cube point of a one-channel sparse lattice: values (M,)
    on the linked vertices, pruned vertices (links < 0) count as 0 (`SparseVoxelGrid.query`)."""
    i0, i1, i2, f0, f1, f2 = lattice_cell(x0, x1, x2, res)
    acc = 0.0
    for a in range(2):
        wa = f0 if a else 1.0 - f0
        for b in range(2):
            wb = f1 if b else 1.0 - f1
            for d in range(2):
                r = links[(i0 + a) + (i1 + b) * res + (i2 + d) * res * res]
                if r >= 0:
                    acc += wa * wb * (f2 if d else 1.0 - f2) * values[r]
    return acc


@numba.njit(parallel=True, cache=True, fastmath=False)
def _corners(x, res, links, rows, w):
    """Same arithmetic as `voxels.trilinear_corners`, then the links lookup."""
    n = x.shape[0]
    for i in numba.prange(n):
        i0, i1, i2, f0, f1, f2 = lattice_cell(x[i, 0], x[i, 1], x[i, 2], res)
        c = 0
        for a in range(2):
            wa = f0 if a else 1.0 - f0
            for b in range(2):
                wb = f1 if b else 1.0 - f1
                for d in range(2):
                    wd = f2 if d else 1.0 - f2
                    rows[i, c] = links[(i0 + a) + (i1 + b) * res + (i2 + d) * res * res]
                    w[i, c] = wa * wb * wd
                    c += 1


def corners(x_unit: Tensor, res: int, links: Tensor) -> tuple[Tensor, Tensor]:
    """Linked rows (N, 8) (-1 = pruned) and trilinear weights (N, 8) of unit-cube points (N, 3)
    (CPU tensors; the torch twin, for other devices: `voxels.linked_corners_torch`)."""
    x = x_unit.detach().contiguous()
    rows = torch.empty((x.shape[0], 8), dtype=torch.int64)
    w = torch.empty((x.shape[0], 8), dtype=x.dtype)
    _corners(x.numpy(), res, links.contiguous().numpy(), rows.numpy(), w.numpy())
    return rows, w


@numba.njit(parallel=True, cache=True, fastmath=False)
def _gather_forward(data, rows, w, out):
    n, k = rows.shape
    c = data.shape[1]
    for i in numba.prange(n):
        for j in range(k):
            r = rows[i, j]
            if r >= 0:
                wij = w[i, j]
                for ch in range(c):
                    out[i, ch] += wij * data[r, ch]


@numba.njit(cache=True, fastmath=False)
def _gather_backward(grad_out, rows, w, grad_data):
    n, k = rows.shape
    c = grad_data.shape[1]
    for i in range(n):
        for j in range(k):
            r = rows[i, j]
            if r >= 0:
                wij = w[i, j]
                for ch in range(c):
                    grad_data[r, ch] += wij * grad_out[i, ch]


class TrilinearGather(torch.autograd.Function):
    """out (N, C) = sum_c w (N, 8) * data[rows (N, 8)]; gradients to data only (w is constant)."""

    @staticmethod
    def forward(ctx, data: Tensor, rows: Tensor, w: Tensor) -> Tensor:
        data_c = data.detach().contiguous()
        rows_c, w_c = rows.contiguous(), w.detach().to(data.dtype).contiguous()
        out = torch.zeros((rows.shape[0], data.shape[1]), dtype=data.dtype)
        _gather_forward(data_c.numpy(), rows_c.numpy(), w_c.numpy(), out.numpy())
        ctx.save_for_backward(rows_c, w_c)
        ctx.num_rows = data.shape[0]
        return out

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        rows, w = ctx.saved_tensors
        grad = torch.zeros((ctx.num_rows, grad_out.shape[1]), dtype=grad_out.dtype)
        _gather_backward(grad_out.contiguous().numpy(), rows.numpy(), w.numpy(), grad.numpy())
        return grad, None, None


def trilinear_gather(data: Tensor, rows: Tensor, w: Tensor) -> Tensor:
    """Fast path on CPU (numba); plain torch elsewhere (e.g. CUDA)."""
    if devices.uses_cpu_kernels(data) and data.dtype in (torch.float32, torch.float64):
        return TrilinearGather.apply(data, rows, w)
    valid = (rows >= 0).to(w.dtype)
    return (data[rows.clamp_min(0)] * (w * valid)[..., None]).sum(dim=1)
