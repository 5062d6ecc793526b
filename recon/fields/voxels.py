"""A sparse voxel grid (Plenoxels, Fridovich-Keil et al. 2022, Sec. 3): values live on the vertices of a
res^3 lattice over the unit cube, stored only where `links` points at a data row; the field
at x is the trilinear interpolation of its 8 surrounding vertices (pruned vertices count as 0).

`query` uses the numba fast path of `voxel_kernels` on the CPU; `query_reference` is its
plain-torch twin (autograd through a gather), used on other devices and in the tests.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from recon import devices
from recon.fields.voxel_kernels import corners, trilinear_gather

# (8, 3) corner offsets in x, y, z order
CORNERS = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])


@functools.lru_cache(maxsize=8)
def _corners_on(device: torch.device) -> Tensor:
    """CORNERS on `device`, copied there once (a copy per lookup would block a GPU step)."""
    with torch.inference_mode(False):
        return CORNERS.to(device)


def linked_corners_torch(x_unit: Tensor, res: int, links: Tensor) -> tuple[Tensor, Tensor]:
    """Linked rows (N, 8) int64 (-1 = pruned) and trilinear weights (N, 8) of unit-cube points
    (N, 3): `trilinear_corners` then the links lookup, the torch twin of
    `voxel_kernels.corners`."""
    idx, w = trilinear_corners(x_unit, res)
    return links[idx].long(), w


def flat_index(ijk: Tensor, res: int) -> Tensor:
    """(..., 3) integer vertex coordinates -> (...,) flat index i + j res + k res^2."""
    return ijk[..., 0] + ijk[..., 1] * res + ijk[..., 2] * res * res


def trilinear_corners(x_unit: Tensor, res: int) -> tuple[Tensor, Tensor]:
    """f(x) = sum_c w_c v_c, w_c = prod_k (f_k if c_k else 1 - f_k), g = x (res - 1), f = g - floor(g).

    x_unit: (N, 3) in [0, 1] (clamped). Returns flat vertex indices (N, 8) and weights (N, 8).
    """
    g = x_unit.clamp(0.0, 1.0) * (res - 1)
    i0 = g.floor().clamp(max=res - 2).long()
    f = g - i0.to(g.dtype)
    corners = _corners_on(x_unit.device)
    idx = flat_index(i0[:, None, :] + corners[None], res)
    w = torch.where(corners[None].bool(), f[:, None, :], 1.0 - f[:, None, :]).prod(dim=-1)
    return idx, w


class SparseVoxelGrid(nn.Module):
    """Vertex data (M, C) for the linked vertices of a res^3 lattice.

    Buffers: `links` (res^3,) int32 row of each vertex or -1 (half the memory of int64: 67 MB at 256^3); `coords` (M,) flat vertex index of
    each row. The data Parameters are split by the caller (e.g. density and SH) so they can have
    their own learning rates; every Parameter has M rows.
    """

    def __init__(self, res: int, channels: dict[str, int], init: dict[str, float]):
        super().__init__()
        self.res = res
        n = res**3
        self.register_buffer("links", torch.arange(n, dtype=torch.int32))
        self.register_buffer("coords", torch.arange(n))
        self.data = nn.ParameterDict(
            {
                k: nn.Parameter(torch.full((n, c), float(init.get(k, 0.0))))
                for k, c in channels.items()
            }
        )

    @property
    def num_rows(self) -> int:
        return self.coords.shape[0]

    def corners(self, x_unit: Tensor) -> tuple[Tensor, Tensor]:
        """Linked rows (N, 8) int64 (-1 = pruned) and trilinear weights (N, 8) of unit-cube
        points (N, 3): numba on the CPU (`voxel_kernels.corners`), else `linked_corners_torch`."""
        if devices.uses_cpu_kernels(x_unit) and x_unit.dtype in (torch.float32, torch.float64):
            return corners(x_unit, self.res, self.links)
        return linked_corners_torch(x_unit.detach(), self.res, self.links)

    def query(self, x_unit: Tensor, names: list[str] | None = None) -> dict[str, Tensor]:
        """Trilinear values at unit-cube points (N, 3) -> {name: (N, C)}."""
        if not devices.uses_cpu_kernels(x_unit) or x_unit.dtype not in (
            torch.float32,
            torch.float64,
        ):
            return self.query_reference(x_unit, names)
        rows, w = corners(x_unit, self.res, self.links)
        return {
            name: trilinear_gather(self.data[name], rows, w)
            for name in names or list(self.data.keys())
        }

    def query_reference(self, x_unit: Tensor, names: list[str] | None = None) -> dict[str, Tensor]:
        """The slow twin of `query`: torch gather, autograd backward."""
        rows, w = linked_corners_torch(x_unit, self.res, self.links)
        w = w * (rows >= 0).to(w.dtype)
        rows = rows.clamp_min(0)
        return {
            name: (self.data[name][rows] * w[..., None]).sum(dim=1)
            for name in names or list(self.data.keys())
        }

    @torch.no_grad()
    def set_rows(
        self, keep_flat: Tensor, values: dict[str, Tensor], res: int | None = None
    ) -> None:
        """Replace the grid: linked vertices `keep_flat` (M,) with data {name: (M, C)}."""
        self.res = res or self.res
        links = torch.full((self.res**3,), -1, dtype=torch.int32, device=keep_flat.device)
        links[keep_flat] = torch.arange(len(keep_flat), dtype=torch.int32, device=keep_flat.device)
        self.links, self.coords = links, keep_flat.clone()
        for name, v in values.items():
            self.data[name] = nn.Parameter(v.contiguous())

    @torch.no_grad()
    def upsample(self, new_res: int, keep_mask_fn) -> None:
        """Resample onto a finer lattice: new vertices inside the dilated linked region take
        the trilinear value of the old field at their position; `keep_mask_fn(dense_old)`
        returns a (res,res,res) bool mask of old vertices worth refining."""
        old = torch.zeros(self.res**3, device=self.links.device)
        old[self.coords] = 1.0
        mask = keep_mask_fn(old.view(self.res, self.res, self.res).bool()).float()
        mask = F.max_pool3d(mask[None, None], 3, stride=1, padding=1)
        fine = (
            F.interpolate(mask, size=(new_res,) * 3, mode="trilinear", align_corners=True)[0, 0] > 0
        )
        flat = fine.reshape(-1).nonzero()[:, 0]
        ijk = torch.stack(
            [flat % new_res, (flat // new_res) % new_res, flat // (new_res * new_res)], -1
        )
        x = ijk.to(torch.float32) / (new_res - 1)
        values = {
            n: torch.cat([self.query(c, [n])[n] for c in x.split(1 << 18)]) for n in self.data
        }
        self.set_rows(flat, values, new_res)

    @torch.no_grad()
    def prune(self, keep_rows: Tensor) -> None:
        """Keep only the data rows where `keep_rows` (M,) is True."""
        self.set_rows(
            self.coords[keep_rows], {n: p.detach()[keep_rows] for n, p in self.data.items()}
        )

    def neighbour_pairs(self, rows: Tensor) -> tuple[Tensor, Tensor]:
        """For data rows (K,), the rows of their +x, +y, +z neighbours where both are linked.
        Returns (a, b) (P,) row pairs for finite differences (total variation)."""
        flat = self.coords[rows]
        ijk = torch.stack(
            [flat % self.res, (flat // self.res) % self.res, flat // (self.res**2)], -1
        )
        a_all, b_all = [], []
        for axis in range(3):
            ok = ijk[:, axis] < self.res - 1
            # a row on the far face looks itself up (in range) and is dropped by `ok`
            nb = self.links[torch.where(ok, flat + (1, self.res, self.res**2)[axis], flat)].long()
            a, b = devices.masked(ok & (nb >= 0), rows, nb)  # one read of the mask, not four
            a_all.append(a)
            b_all.append(b)
        return torch.cat(a_all), torch.cat(b_all)
