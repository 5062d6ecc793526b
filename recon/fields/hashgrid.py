"""Multiresolution hash encoding (Müller et al. 2022, Sec. 3).

L levels with resolutions N_l = floor(N_min b^l), b = exp((ln N_max - ln N_min) / (L - 1)).
Level l is a grid of (N_l + 1)^3 vertices over the unit cube, each holding F features. A level
is stored densely, index = x + y (N_l + 1) + z (N_l + 1)^2, while (N_l + 1)^3 <= T; beyond that
its vertices share T slots through the spatial hash

    h(x, y, z) = (x * 1  XOR  y * 2654435761  XOR  z * 805459861) mod T

(evaluated in int64: y * 2654435761 < 2^63 for any N_l < 3e9, so nothing overflows). A point
is encoded by trilinear interpolation of its cell's 8 corner features at every level,
concatenated: (N, 3) in [0, 1]^3 -> (N, L F).

All levels live in ONE flat table (total_entries, F) at per-level offsets, so an encode is one
gather. Two implementations with the same maths: `hash_encode_torch` (any device, autograd for
features and positions) and a numba CPU kernel (`hash_encode`, features only), which avoids
materialising the (N, L, 8) index/weight tensors; tests compare them on values and gradients.
The torch path reads the per-level constants from tensors made once per layout and device
(`level_tensors`): an encode on a GPU copies nothing from the host.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numba
import numpy as np
import torch
from torch import Tensor, nn

from recon import devices

PRIMES = (1, 2654435761, 805459861)


def growth_factor(n_levels: int, n_min: int, n_max: int) -> float:
    """b = exp((ln N_max - ln N_min) / (L - 1)); worked example (Müller et al. 2022, eq. 3): (16, 16, 2048) -> 1.3819."""
    if n_levels == 1:
        return 1.0
    return math.exp((math.log(n_max) - math.log(n_min)) / (n_levels - 1))


def level_layout(n_levels: int, n_min: int, n_max: int, table_size: int) -> dict[str, list[int]]:
    """Per-level resolution N_l = floor(N_min b^l), entries min((N_l + 1)^3, T), dense flag
    and offset into the flat table. Problem 4 gives 6,098,925 entries (x F = 2: 12,197,850)."""
    b = growth_factor(n_levels, n_min, n_max)
    res = [math.floor(n_min * b**level) for level in range(n_levels)]
    dense = [(n + 1) ** 3 <= table_size for n in res]
    sizes = [(n + 1) ** 3 if d else table_size for n, d in zip(res, dense)]
    offsets = [sum(sizes[:level]) for level in range(n_levels)]
    return {"resolution": res, "size": sizes, "dense": dense, "offset": offsets}


class LevelTensors(NamedTuple):
    """A `level_layout` as tensors on one device: resolution, size, offset (L,) int64, dense
    (L,) bool, and the corner offsets bits (8, 3) int64, corner c = (c & 1, c >> 1 & 1, c >> 2 & 1)."""

    resolution: Tensor
    size: Tensor
    offset: Tensor
    dense: Tensor
    bits: Tensor


def level_tensors(layout: dict[str, list[int]], device: torch.device) -> LevelTensors:
    """The layout's constants on `device`, made on the first call for this layout and device and
    kept (constants: a host-to-device copy per encode would block a GPU step)."""
    key = tuple(tuple(layout[k]) for k in ("resolution", "size", "offset", "dense"))
    return _level_tensors(key, torch.device(device))


@functools.lru_cache(maxsize=64)
def _level_tensors(key: tuple, device: torch.device) -> LevelTensors:
    resolution, size, offset, dense = key
    bits = [[(c >> k) & 1 for k in range(3)] for c in range(8)]
    with torch.inference_mode(False):  # usable by autograd wherever they were first made
        return LevelTensors(
            torch.tensor(resolution, dtype=torch.int64, device=device),
            torch.tensor(size, dtype=torch.int64, device=device),
            torch.tensor(offset, dtype=torch.int64, device=device),
            torch.tensor(dense, dtype=torch.bool, device=device),
            torch.tensor(bits, dtype=torch.int64, device=device),
        )


def spatial_hash(ijk: Tensor, table_size: int | Tensor) -> Tensor:
    """(x * 1 ^ y * 2654435761 ^ z * 805459861) mod T for int64 vertices (..., 3) -> (...);
    T an int or a tensor broadcastable to (...)."""
    h = (ijk[..., 0] * PRIMES[0]) ^ (ijk[..., 1] * PRIMES[1]) ^ (ijk[..., 2] * PRIMES[2])
    return h % table_size


def corner_indices_and_weights(x: Tensor, layout: dict[str, list[int]]) -> tuple[Tensor, Tensor]:
    """Flat-table rows (N, L, 8) int64 and trilinear weights (N, L, 8) of every corner.

    pos = x N_l; the cell is i0 = floor(pos) clamped to [0, N_l - 1] so x = 1 interpolates the
    last cell with fraction 1 (points on faces/corners use the cell below). Corner c has bits
    (c & 1, c >> 1 & 1, c >> 2 & 1) for (x, y, z).
    """
    lv = level_tensors(layout, x.device)
    res, bits = lv.resolution, lv.bits  # (L,), (8, 3)
    pos = x.clamp(0.0, 1.0)[:, None, :] * res[None, :, None].to(x.dtype)  # (N, L, 3)
    i0 = torch.minimum(pos.floor().long(), (res - 1)[None, :, None])
    frac = pos - i0.to(x.dtype)
    ijk = i0[:, :, None, :] + bits  # (N, L, 8, 3)
    w = torch.where(bits.bool(), frac[:, :, None, :], 1.0 - frac[:, :, None, :]).prod(dim=-1)
    stride = res + 1
    dense_idx = ijk[..., 0] + stride[:, None] * (ijk[..., 1] + stride[:, None] * ijk[..., 2])
    idx = torch.where(lv.dense[:, None], dense_idx, spatial_hash(ijk, lv.size[:, None]))
    return idx + lv.offset[:, None], w


def gather_rows(table: Tensor, rows: Tensor) -> Tensor:
    """table[rows]: rows (...) int64 of table (E, F) -> (..., F), through `index_select`, whose
    backward adds into the table's gradient (`index_add_`: atomic adds on a GPU) where advanced
    indexing's backward first sorts every index (an Instant-NGP step on an H200 spent 9.6 of
    its 28 ms in that backward and its sorts)."""
    return table.index_select(0, rows.reshape(-1)).view(*rows.shape, table.shape[-1])


def hash_encode_torch(x: Tensor, table: Tensor, layout: dict[str, list[int]]) -> Tensor:
    """Pure-torch encoding: sum_c w_c table[row_c] per level. x (N, 3), table (E, F) -> (N, L F).
    Differentiable in both table and x (the reference twin, and the path off CPU)."""
    idx, w = corner_indices_and_weights(x, layout)
    feats = gather_rows(table, idx)  # (N, L, 8, F)
    return (feats * w[..., None].to(table.dtype)).sum(dim=-2).flatten(start_dim=1)


@numba.njit(cache=True, inline="always")
def _cell(x, nf, n):
    """(i0, frac) of one coordinate x in [0, 1] on resolution n (nf = n in x's dtype, so the
    product rounds exactly as in `corner_indices_and_weights`)."""
    pos = x * nf
    i0 = min(np.int64(math.floor(pos)), n - 1)
    return i0, pos - i0


@numba.njit(cache=True, inline="always")
def _level(res, resf, size, dense, offset, lv):
    """Level lv's constants for `_fill_corners`: (n, nf, size, offset, dense, stride_y,
    stride_z, size is a power of 2). Strides: dense (N+1), (N+1)^2; hashed the primes P2, P3."""
    n, dn, sz = res[lv], dense[lv], size[lv]
    stride_y = n + 1 if dn else np.int64(2654435761)
    stride_z = (n + 1) * (n + 1) if dn else np.int64(805459861)
    return n, resf[lv], sz, offset[lv], dn, stride_y, stride_z, sz & (sz - 1) == 0


@numba.njit(cache=True, inline="always")
def _fill_corners(x, p, n, nf, dn, sz, pow2, stride_y, stride_z, off, rows, ws):  # pragma: no cover
    """rows[c], ws[c] for the 8 corners c = dx + 2 dy + 4 dz of point p's cell on one level.
    Per-axis index terms are combined: dense  x + y (N+1) + z (N+1)^2,  hashed  x ^ y P2 ^ z P3."""
    ix, fx = _cell(x[p, 0], nf, n)
    iy, fy = _cell(x[p, 1], nf, n)
    iz, fz = _cell(x[p, 2], nf, n)
    c = 0
    for dz in range(2):
        wz = fz if dz else 1 - fz
        tz = (iz + dz) * stride_z
        for dy in range(2):
            wyz = wz * (fy if dy else 1 - fy)
            ty = (iy + dy) * stride_y
            for dx in range(2):
                ws[c] = wyz * (fx if dx else 1 - fx)
                if dn:
                    rows[c] = off + ix + dx + ty + tz
                else:
                    h = (ix + dx) ^ ty ^ tz
                    rows[c] = off + (h & (sz - 1) if pow2 else h % sz)  # h >= 0: mask == mod
                c += 1


@numba.njit(parallel=True, cache=True)
def _hash_backward(x, grad_table, grad_feats, res, resf, size, dense, offset):  # pragma: no cover
    """grad_table[row_c, k] += w_c grad_feats[l, p, k], the backward of `_hash_forward`.

    Level-major and parallel over levels: a thread streams every point through ONE level's
    slice of the table (which stays in cache, and which no other thread writes, so the
    scatter has no races); grad_feats is (L, N, F) so each level reads one contiguous block.
    """
    n_pts, n_levels, n_feat = x.shape[0], res.shape[0], grad_table.shape[1]
    for lv in numba.prange(n_levels):
        n, nf, sz, off, dn, stride_y, stride_z, pow2 = _level(res, resf, size, dense, offset, lv)
        rows = np.empty(8, np.int64)  # per-thread scratch, reused for every point
        ws = np.empty(8, x.dtype)
        for p in range(n_pts):
            _fill_corners(x, p, n, nf, dn, sz, pow2, stride_y, stride_z, off, rows, ws)
            for k in range(n_feat):
                g = grad_feats[lv, p, k]
                for c in range(8):
                    grad_table[rows[c], k] += ws[c] * g


@numba.njit(parallel=True, cache=True)
def _hash_forward(x, table, feats, res, resf, size, dense, offset):  # pragma: no cover
    """feats[p, l F + k] = sum_c w_c table[row_c, k], point-major (N, L F): parallel over blocks
    of 2,048 points, each block through one level at a time (that level's slice of the table
    stays in cache), so no (L, N, F) -> (N, L F) transpose follows (lego-200 ngp render 283 ->
    273 ms a frame against the level-major kernel; the same values to the bit)."""
    n_pts, n_levels, n_feat = x.shape[0], res.shape[0], table.shape[1]
    block = 2048
    for b in numba.prange((n_pts + block - 1) // block):
        rows = np.empty(8, np.int64)
        ws = np.empty(8, x.dtype)
        for lv in range(n_levels):
            n, nf, sz, off, dn, stride_y, stride_z, pow2 = _level(
                res, resf, size, dense, offset, lv
            )
            for p in range(b * block, min((b + 1) * block, n_pts)):
                _fill_corners(x, p, n, nf, dn, sz, pow2, stride_y, stride_z, off, rows, ws)
                for k in range(n_feat):
                    acc = ws[0] * table[rows[0], k]
                    for c in range(1, 8):
                        acc += ws[c] * table[rows[c], k]
                    feats[p, lv * n_feat + k] = acc


def _layout_arrays(layout: dict[str, list[int]]) -> tuple[np.ndarray, ...]:
    return tuple(
        np.asarray(layout[k], dtype=np.int64) for k in ("resolution", "size", "offset")
    ) + (np.asarray(layout["dense"], dtype=np.bool_),)


def _encode(xs: Tensor, table: Tensor, layout: dict) -> Tensor:
    """numba encoding of clamped positions xs (N, 3) -> (N, L F)."""
    res, size, offset, dense = _layout_arrays(layout)
    resf = res.astype(xs.numpy().dtype)
    out = torch.empty((xs.shape[0], len(res) * table.shape[1]), dtype=table.dtype)
    tab = table.detach().contiguous().numpy()
    _hash_forward(xs.numpy(), tab, out.numpy(), res, resf, size, dense, offset)
    return out


def _encode_table_grad(xs: Tensor, grad_out: Tensor, layout: dict, table_shape) -> Tensor:
    """The table's gradient (E, F) of the encoding at xs (N, 3) given grad_out (N, L F)."""
    res, size, offset, dense = _layout_arrays(layout)
    grad_table = torch.zeros(table_shape, dtype=grad_out.dtype)
    L, F = len(res), table_shape[1]
    g = grad_out.detach().reshape(grad_out.shape[0], L, F).permute(1, 0, 2).contiguous().numpy()
    resf = res.astype(xs.numpy().dtype)
    _hash_backward(xs.numpy(), grad_table.numpy(), g, res, resf, size, dense, offset)
    return grad_table


class _HashEncodeCPU(torch.autograd.Function):
    """numba forward/backward; gradient w.r.t. the table only (positions are data)."""

    @staticmethod
    def forward(ctx, x: Tensor, table: Tensor, layout: dict) -> Tensor:
        xs = x.detach().clamp(0.0, 1.0).contiguous()
        ctx.save_for_backward(xs)
        ctx.layout, ctx.table_shape = layout, table.shape
        return _encode(xs, table, layout)

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        (xs,) = ctx.saved_tensors
        return None, _encode_table_grad(xs, grad_out, ctx.layout, ctx.table_shape), None


def hash_encode(x: Tensor, table: Tensor, layout: dict[str, list[int]]) -> Tensor:
    """Multiresolution hash encoding x (N, 3) in [0, 1]^3 -> (N, L F) (see module docstring).

    CPU tensors whose positions need no gradient use the numba kernel; anything else (CUDA,
    d/dx by autograd) uses `hash_encode_torch`. Both give the same values and table gradients.
    The Jacobian in x, for normals and an eikonal loss, is in `recon.fields.hashgrid_jacobian`.
    """
    if devices.uses_cpu_kernels(x) and not x.requires_grad and x.dtype == table.dtype:
        return _HashEncodeCPU.apply(x, table, layout)
    return hash_encode_torch(x, table, layout)


class HashGrid(nn.Module):
    """Learnable multiresolution hash encoding: one flat table (total_entries, F) of features
    initialised U(-1e-4, 1e-4) as in Instant-NGP. forward: (N, 3) in [0, 1]^3 -> (N, L F)."""

    def __init__(
        self,
        n_levels: int = 16,
        n_features: int = 2,
        log2_table_size: int = 19,
        n_min: int = 16,
        n_max: int = 2048,
    ):
        super().__init__()
        self.layout = level_layout(n_levels, n_min, n_max, 2**log2_table_size)
        entries = sum(self.layout["size"])
        self.table = nn.Parameter(torch.empty(entries, n_features).uniform_(-1e-4, 1e-4))
        self.out_dim = n_levels * n_features

    def forward(self, x: Tensor) -> Tensor:
        return hash_encode(x, self.table, self.layout)
