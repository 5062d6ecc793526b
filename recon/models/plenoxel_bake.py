"""A trained neural field (ngp, nerf: any model with `radiance`) baked into a Plenoxels lattice,
so it renders at the lattice's speed. As PlenOctrees (Yu et al. 2021, "PlenOctrees for
Real-time Rendering of Neural Radiance Fields", sec. 4.2-4.3) converts a NeRF: evaluate the
density at every vertex that can matter, project the view-dependent colour onto spherical
harmonics from a set of sampled directions, then fine-tune the grid on the training photos
(the plenoxel model's own training; `PlenoxelModel` calls `bake_lattice` at its first step).

The colour fit is in logit space, because a Plenoxels vertex holds SH coefficients of the
colour before its sigmoid: c = argmin sum_d (Y(d) . c - logit rgb(d))^2 = pinv(Y) logit(rgb).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from recon.fields.sh import sh_basis
from recon.volrend.contraction import unit_cube_to_scene
from recon.volrend.occupancy import cells_of


def fibonacci_directions(n: int) -> Tensor:
    """n (n, 3) unit vectors spread evenly over the sphere (the Fibonacci lattice, Gonzalez
    2010): z_i = 1 - (2 i + 1) / n, azimuth i times the golden angle pi (3 - sqrt 5).
    Example: n = 2 -> (0.866, 0, 0.5) and (-0.639, 0.585, -0.5)."""
    i = torch.arange(n, dtype=torch.float64)
    z = 1.0 - (2.0 * i + 1.0) / n
    r = (1.0 - z * z).clamp_min(0.0).sqrt()
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return torch.stack([r * phi.cos(), r * phi.sin(), z], dim=-1).float()


def fit_sh_logits(rgb: Tensor, basis: Tensor, eps: float = 1e-3) -> Tensor:
    """SH coefficients (N, K, 3) whose sigmoid best matches colours rgb (N, D, 3) seen along
    D directions with SH basis values basis (D, K), in the least-squares sense on the logits
    (the colours clamped to [eps, 1 - eps] first): pinv(basis) (K, D) applied to logit(rgb).
    Exact when the logits are a combination of the K basis functions and the D >= K
    directions make basis of rank K."""
    logits = torch.logit(rgb.float().clamp(eps, 1.0 - eps))
    return torch.einsum("kd,ndc->nkc", torch.linalg.pinv(basis.double()).float(), logits)


def lattice_points(flat: Tensor, res: int) -> Tensor:
    """Unit-cube positions (M, 3) of lattice vertices with flat indices i + j res + k res^2
    (M,): (i, j, k) / (res - 1), the vertex layout of `SparseVoxelGrid`."""
    ijk = torch.stack([flat % res, (flat // res) % res, flat // (res * res)], dim=-1)
    return ijk.float() / (res - 1)


def dilate(mask: Tensor, res: int) -> Tensor:
    """A flat (res^3,) bool mask of a cube grown by one cell in every direction (3 x 3 x 3)."""
    grown = F.max_pool3d(mask.view(1, 1, res, res, res).float(), 3, stride=1, padding=1)
    return grown.reshape(-1) > 0


def vertices_in_cells(occupied: Tensor, cells: int, res: int) -> Tensor:
    """The vertices (res^3,) bool of a res^3 lattice inside the cells of a cells^3 occupancy
    bitfield (x fastest, as `OccupancyGrid`) grown by one cell: where a field can be non-zero."""
    grown = dilate(occupied, cells)
    inside = torch.zeros(res**3, dtype=torch.bool)
    for part in torch.arange(res**3).split(1 << 22):
        idx, ok = cells_of(lattice_points(part, res), cells)
        inside[part] = grown[idx] & ok
    return inside


@torch.no_grad()
def bake_lattice(
    source,
    res: int,
    aabb: Tensor,
    unbounded: bool,
    sh_degree: int,
    n_directions: int,
    density_scale: float,
    min_density: float,
    candidates: Tensor | None = None,
    chunk: int = 1 << 15,
) -> tuple[Tensor, Tensor, Tensor]:
    """The vertices of a res^3 lattice worth keeping and their Plenoxels values, from `source`
    (a model with `radiance` and `density` at normalized points):
    density d = sigma / density_scale (Plenoxels' sigma = relu(d) density_scale), kept where
    some vertex of the 3 x 3 x 3 neighbourhood has d > min_density; SH coefficients fitted to
    the colours along `n_directions` Fibonacci directions (`fit_sh_logits`).
    candidates: (res^3,) bool, the vertices to evaluate at all (None: every one).
    Returns (flat vertex indices (M,), density (M, 1), SH (M, 3 K) laid out colour-major,
    as `PlenoxelModel` views it: (M, 3, K))."""
    flat = torch.arange(res**3) if candidates is None else candidates.nonzero()[:, 0]
    device = aabb.device

    def world(f: Tensor) -> Tensor:
        return unit_cube_to_scene(lattice_points(f, res).to(device), aabb, unbounded)

    density = torch.zeros(res**3)
    for part in flat.split(chunk):
        x = world(part)
        ok = x.isfinite().all(-1)
        sigma = torch.zeros(len(part), device=device)
        if ok.any():
            sigma[ok] = source.density(x[ok]).float()
        density[part] = (sigma / density_scale).cpu()
    keep = dilate(density > min_density, res)
    if candidates is not None:
        keep &= candidates
    kept = keep.nonzero()[:, 0]
    directions = fibonacci_directions(n_directions).to(device)
    basis = sh_basis(sh_degree, directions)  # (D, K)
    sh = []
    for part in kept.split(max(1, chunk // n_directions * 8)):
        x = world(part)
        ok = x.isfinite().all(-1)
        coeffs = torch.zeros(len(part), basis.shape[1], 3, device=device)
        if ok.any():
            _, rgb = source.radiance(x[ok], directions)
            coeffs[ok] = fit_sh_logits(rgb, basis)
        sh.append(coeffs.transpose(1, 2).reshape(len(part), -1).cpu())
    K3 = 3 * basis.shape[1]
    sh = torch.cat(sh) if sh else torch.zeros(0, K3)
    return kept, density[kept][:, None], sh
