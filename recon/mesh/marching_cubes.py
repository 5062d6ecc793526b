"""Iso-surfaces of fields sampled on a regular grid (Lorensen & Cline 1987; Lewiner et al. 2003
via `skimage.measure.marching_cubes`), oriented outward, in the frame of the box.

The grid: origin = aabb_min, isotropic spacing h, n_a = ceil(extent_a / h) + 1 samples per axis
(the last sample may lie up to h past aabb_max). Field callables take points (N, 3) -> (N,).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import numpy as np
import torch
import trimesh
from skimage.measure import marching_cubes
from torch import Tensor

Field = Callable[[Tensor], Tensor]


def choose_density_threshold(voxel_size: float, opacity: float = 0.5) -> float:
    """sigma* = -ln(1 - opacity) / voxel_size  (= ln 2 / voxel_size for opacity 0.5).

    The density at which a slab one voxel thick reaches `opacity` (alpha = 1 - exp(-sigma h),
    Max 1995): the surface is where a ray crossing one voxel would be half stopped.
    Chosen over a fixed sigma because a fixed value depends on the scene's scale, while this
    one is stated in the units of the grid it is used on. Example: the box [-1, 1]^3 at 256
    samples per side has h = 2/255 and sigma* = ln 2 * 127.5 = 88.4.
    """
    if not 0.0 < opacity < 1.0 or voxel_size <= 0:
        raise ValueError("choose_density_threshold: need 0 < opacity < 1 and voxel_size > 0")
    return -math.log1p(-opacity) / voxel_size


def soft_field_threshold(voxel_threshold: float, surface_density: np.ndarray) -> float:
    """min(sigma*_voxel, median sigma(x_s)) over points x_s where training renders put the surface.

    A field softer than one voxel (early in training, or a blurry region) never reaches
    sigma*_voxel = ln 2 / h and its level set at that value is empty or shredded; its own renders
    still show a surface at the expected depth, so the level through the median of those points
    is used instead. A field sharper than one voxel keeps sigma*_voxel. Example: sigma*_voxel =
    150 and densities (4, 9, 40) at the rendered surface -> 9; densities (400, 900) -> 150.
    """
    values = np.asarray(surface_density, np.float64).reshape(-1)
    values = values[np.isfinite(values)]
    if len(values) == 0:
        return float(voxel_threshold)
    return float(min(voxel_threshold, np.median(values)))


def grid_shape(aabb, resolution: int) -> tuple[tuple[int, int, int], float]:
    """Samples per axis and spacing h = (longest side) / (resolution - 1) for aabb (2, 3)."""
    lo, hi = np.asarray(aabb, np.float64)
    if resolution < 2 or np.any(hi <= lo):
        raise ValueError("grid_shape: need resolution >= 2 and aabb_min < aabb_max")
    h = float((hi - lo).max()) / (resolution - 1)
    shape = tuple(int(n) for n in np.ceil((hi - lo) / h - 1e-9).astype(int) + 1)
    return shape, h


def grid_slabs(
    origin, spacing: float, shape: tuple[int, int, int], chunk: int, device=None
) -> Iterator[tuple[slice, Tensor]]:
    """Batches of grid points in C order: (flat slice, points (n, 3)) for whole x-slices.

    Point (i, j, k) = origin + h (i, j, k). Each batch holds max(1, chunk // (Y Z)) x-slices,
    built from one precomputed (Y Z, 2) plane: no integer division on the hot path.
    """
    nx, ny, nz = shape
    origin = torch.as_tensor(origin, dtype=torch.float32, device=device)
    y = origin[1] + spacing * torch.arange(ny, device=device, dtype=torch.float32)
    z = origin[2] + spacing * torch.arange(nz, device=device, dtype=torch.float32)
    plane = torch.stack(torch.meshgrid(y, z, indexing="ij"), dim=-1).reshape(1, ny * nz, 2)
    step = max(1, chunk // (ny * nz))
    for i0 in range(0, nx, step):
        i1 = min(i0 + step, nx)
        x = origin[0] + spacing * torch.arange(i0, i1, device=device, dtype=torch.float32)
        xs = x[:, None, None].expand(-1, ny * nz, 1)
        points = torch.cat([xs, plane.expand(i1 - i0, -1, -1)], dim=-1).reshape(-1, 3)
        yield slice(i0 * ny * nz, i1 * ny * nz), points


def evaluate_grid(
    fn: Field,
    origin,
    spacing: float,
    shape: tuple[int, int, int],
    chunk: int = 1 << 18,
    device: str | torch.device = "cpu",
) -> np.ndarray:
    """fn at origin + h (i, j, k) for all grid indices, in batches of about `chunk` points
    (at least one x-slice) -> (X, Y, Z) float32.

    Non-finite outputs are replaced by 0 (no density / no surface) so a single NaN cannot
    break the extraction.
    """
    out = np.empty(int(np.prod(shape)), dtype=np.float32)
    with torch.no_grad():
        for flat, points in grid_slabs(origin, spacing, shape, chunk, device):
            out[flat] = fn(points).reshape(-1).float().cpu().numpy()
    return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0).reshape(shape)


def mesh_from_grid(
    values: np.ndarray, origin, spacing: float, level: float, valid_cubes: np.ndarray | None = None
) -> trimesh.Trimesh:
    """The surface {values = level} of an (X, Y, Z) grid, with `values > level` as the inside.

    Vertices are in the box frame: origin + h * (grid coordinates). Faces are wound so that
    normals point outward, toward decreasing values. `valid_cubes` (X-1, Y-1, Z-1) bool drops
    the faces of cubes that have a corner without data (e.g. unobserved TSDF voxels).
    Returns an empty mesh when the level is not crossed.
    """
    values = np.asarray(values, np.float32)
    if not values.min() < level < values.max():
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False)
    grid_vertices, faces, _, _ = marching_cubes(values, level=level, gradient_direction="descent")
    faces = faces[:, ::-1]  # skimage winds these clockwise seen from outside; make them CCW
    if valid_cubes is not None:
        cube = np.floor(grid_vertices[faces].mean(axis=1)).astype(np.int64)
        cube = np.minimum(cube, np.array(valid_cubes.shape) - 1)
        faces = faces[valid_cubes[cube[:, 0], cube[:, 1], cube[:, 2]]]
    vertices = np.asarray(origin, np.float64) + spacing * grid_vertices.astype(np.float64)
    mesh = trimesh.Trimesh(vertices, np.ascontiguousarray(faces), process=False)
    mesh.remove_unreferenced_vertices()
    return mesh


def vertex_colors(
    color_fn: Field, vertices: np.ndarray, chunk: int = 1 << 16, device: str | torch.device = "cpu"
) -> np.ndarray:
    """color_fn (N, 3) -> (N, 3) in [0, 1] at the vertices, chunked -> (N, 4) uint8 RGBA."""
    points = torch.as_tensor(vertices, dtype=torch.float32, device=device)
    rgb = np.empty((len(points), 3), np.float32)
    with torch.no_grad():
        for start in range(0, len(points), chunk):
            rgb[start : start + chunk] = color_fn(points[start : start + chunk]).float().cpu()
    rgba = np.concatenate([np.clip(rgb, 0, 1) * 255 + 0.5, np.full((len(rgb), 1), 255.0)], 1)
    return rgba.astype(np.uint8)


def extract_density_mesh(
    density_fn: Field,
    aabb,
    resolution: int,
    threshold: float | None = None,
    chunk: int = 1 << 18,
    color_fn: Field | None = None,
    device: str | torch.device = "cpu",
) -> trimesh.Trimesh:
    """Mesh of {x : sigma(x) = threshold} inside aabb (2, 3), normals toward lower density.

    `resolution` samples along the longest side of the box (isotropic voxels). threshold
    None -> `choose_density_threshold(h)`. Vertex colours from `color_fn` when given.
    """
    shape, h = grid_shape(aabb, resolution)
    origin = np.asarray(aabb, np.float64)[0]
    if threshold is None:
        threshold = choose_density_threshold(h)
    density = evaluate_grid(density_fn, origin, h, shape, chunk, device)
    mesh = mesh_from_grid(density, origin, h, threshold)
    if color_fn is not None and len(mesh.vertices) > 0:
        mesh.visual.vertex_colors = vertex_colors(color_fn, mesh.vertices, chunk, device)
    return mesh
