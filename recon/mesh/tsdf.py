"""TSDF fusion of z-depth (+ colour) maps into a voxel grid (Curless & Levoy 1996; KinectFusion,
Newcombe et al. 2011), then marching cubes at 0: a mesh from any method that renders depth.

Per voxel x and view c with x_c = cam_from_world_c x, depth D_c at the pixel containing the
projection of x_c:  sdf_c = D_c - z(x_c)  (projective, along the optical axis),
tsdf_c = min(1, sdf_c / trunc), used when sdf_c >= -trunc (voxels farther behind the surface
are occluded, not observed). The grid keeps the weighted running average
T <- (W T + sum_c w_c tsdf_c) / (W + sum_c w_c), W <- W + sum_c w_c, with w_c = 1; colour is
averaged the same way over views with |sdf_c| < trunc only, so free space far in front of
another surface does not tint the surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from torch import Tensor

from recon.cameras import Cameras
from recon.mesh.marching_cubes import grid_shape, grid_slabs, mesh_from_grid


@dataclass(frozen=True)
class TSDFConfig:
    """TSDF fusion settings; lengths are relative to the longest side of the AABB."""

    resolution: int = 192
    """Voxels along the longest side of the box (voxel size = side / resolution). Memory is
    24 bytes per voxel: 192 -> ~170 MB for a cube."""
    truncation: float = 0.02
    """Truncation distance as a fraction of the longest side; raised to at least 2 voxels,
    below which the zero crossing is not resolved."""
    chunk: int = 1 << 22
    """Voxel-view pairs projected per batch (peak memory ~ 60 bytes per pair)."""


@dataclass
class TSDFVolume:
    """Dense fusion state; grid point (i, j, k) is at origin + voxel_size * (i, j, k)."""

    origin: Tensor  # (3,)
    voxel_size: float
    truncation: float
    tsdf: Tensor  # (X, Y, Z) running average of the truncated sdf, in [-1, 1]
    weight: Tensor  # (X, Y, Z) number of views that observed the voxel
    color: Tensor  # (X, Y, Z, 3) running average colour of near-surface observations
    color_weight: Tensor  # (X, Y, Z)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.tsdf.shape)


def tsdf_volume(aabb, config: TSDFConfig, device: str | torch.device = "cpu") -> TSDFVolume:
    """An empty volume over aabb (2, 3): no voxel observed yet (weight 0)."""
    shape, h = grid_shape(aabb, config.resolution + 1)
    side = h * config.resolution
    zeros = torch.zeros(shape, dtype=torch.float32, device=device)
    return TSDFVolume(
        origin=torch.as_tensor(np.asarray(aabb, np.float64)[0], dtype=torch.float32, device=device),
        voxel_size=h,
        truncation=max(config.truncation * side, 2.0 * h),
        tsdf=torch.ones_like(zeros),
        weight=zeros,
        color=torch.zeros(shape + (3,), dtype=torch.float32, device=device),
        color_weight=zeros.clone(),
    )


def project_tsdf(
    points: Tensor, cameras: Cameras, depths: Tensor, rgbs: Tensor | None, truncation: float
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Sums over the C views of one batch of voxels, all views at once.

    points: (N, 3) world; depths: (C, H, W) z-depths (invalid: <= 0 or not finite; a padded
    batch is fine, pixels past each camera's width/height are ignored); rgbs: (C, H, W, 3)
    in [0, 1] or None. Returns sum_c w_c tsdf_c (N,), sum_c w_c (N,),
    sum_c v_c rgb_c (N, 3), sum_c v_c (N,) with v_c = w_c [|sdf_c| < trunc].
    """
    C, H, W = depths.shape
    depths = torch.where(torch.isfinite(depths) & (depths > 0), depths, torch.nan)
    # K [R | t] folded into one (C, 3, 4) matrix: a single batched product on the hot path
    P = cameras.K @ cameras.cam_from_world[:, :3, :]
    hom = torch.einsum("cij,nj->cni", P[:, :, :3], points) + P[:, None, :, 3]  # (C, N, 3)
    z = hom[..., 2]
    u, v = hom[..., 0] / z, hom[..., 1] / z
    inside = (z > 0) & (u >= 0) & (v >= 0)  # NaN (a voxel at a camera centre) fails these
    inside &= (u < cameras.width[:, None]) & (v < cameras.height[:, None])
    u, v = torch.where(inside, u, 0.0), torch.where(inside, v, 0.0)
    flat = v.long().clamp(max=H - 1) * W + u.long().clamp(max=W - 1)  # pixel containing (u, v)
    depth = depths.reshape(C, H * W).gather(1, flat)  # (C, N), NaN where no valid depth
    sdf = depth - z
    observed = inside & (sdf >= -truncation)
    w = observed.to(points.dtype)
    tsdf = torch.where(observed, (sdf / truncation).clamp(max=1.0), 0.0)
    near = observed & (sdf.abs() < truncation)
    color_sum = points.new_zeros(points.shape)
    if rgbs is not None:  # only the few near-surface pairs carry colour: gather just those
        cam, point = near.nonzero(as_tuple=True)
        rgb = rgbs.reshape(C, H * W, 3)[cam, flat[cam, point]]
        color_sum.index_add_(0, point, rgb.to(points.dtype))
    return tsdf.sum(0), w.sum(0), color_sum, near.sum(0).to(points.dtype)


def integrate(
    volume: TSDFVolume,
    cameras: Cameras,
    depths: Tensor,
    rgbs: Tensor | None = None,
    chunk: int = TSDFConfig.chunk,
) -> TSDFVolume:
    """Fuse C views (depths (C, H, W), rgbs (C, H, W, 3) or None) into `volume`, in place.

    Call repeatedly with batches of views to bound memory; the running average makes the
    result independent of the batching. Returns the volume for chaining.
    """
    device, dtype = volume.tsdf.device, volume.tsdf.dtype
    cameras = cameras.to(device=device, dtype=dtype)
    depths = depths.to(device=device, dtype=dtype)
    if rgbs is not None:
        rgbs = rgbs.to(device=device, dtype=dtype) / (255.0 if rgbs.dtype == torch.uint8 else 1.0)
    tsdf, weight = volume.tsdf.view(-1), volume.weight.view(-1)
    color, color_weight = volume.color.view(-1, 3), volume.color_weight.view(-1)
    voxels_per_batch = max(1, chunk // max(1, len(cameras)))
    slabs = grid_slabs(volume.origin, volume.voxel_size, volume.shape, voxels_per_batch, device)
    for flat, points in slabs:  # flat slices are views into the grid: updated in place
        s_t, s_w, s_c, s_v = project_tsdf(points, cameras, depths, rgbs, volume.truncation)
        _running_average(tsdf[flat], weight[flat], s_t, s_w)
        _running_average(color[flat], color_weight[flat], s_c, s_v)
    return volume


def _running_average(mean: Tensor, weight: Tensor, value_sum: Tensor, weight_sum: Tensor) -> None:
    """In place: mean <- (W mean + S) / (W + w), W <- W + w, where W + w > 0."""
    new_weight = weight + weight_sum
    update = new_weight > 0
    ratio = (weight / new_weight.clamp_min(1e-12))[update]
    if mean.dim() == 2:
        mean[update] = ratio[:, None] * mean[update] + value_sum[update] / new_weight[update, None]
    else:
        mean[update] = ratio * mean[update] + value_sum[update] / new_weight[update]
    weight.copy_(new_weight)


def sample_colors(volume: TSDFVolume, points: Tensor) -> Tensor:
    """Trilinear colour (N, 3) at points (N, 3), weighted by colour weight (unobserved
    corners do not count): sum_k b_k v_k c_k / sum_k b_k v_k over the 8 corners."""
    g = (points - volume.origin) / volume.voxel_size
    shape = torch.tensor(volume.shape, device=points.device)
    base = torch.floor(g).long().clamp(torch.zeros_like(shape), shape - 2)
    frac = (g - base).clamp(0, 1)
    num = points.new_zeros(points.shape)
    den = points.new_zeros(points.shape[0])
    for corner in range(8):
        offset = torch.tensor([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1], device=g.device)
        b = torch.where(offset.bool(), frac, 1 - frac).prod(-1)
        i, j, k = (base + offset).unbind(-1)
        bv = b * volume.color_weight[i, j, k]
        num += bv[:, None] * volume.color[i, j, k]
        den += bv
    return num / den.clamp_min(1e-12)[:, None]


def tsdf_mesh(volume: TSDFVolume, with_colors: bool = True) -> trimesh.Trimesh:
    """Marching cubes at TSDF = 0 over cubes whose 8 corners were all observed, outward."""
    observed = (volume.weight > 0).cpu().numpy()
    valid = np.ones(tuple(s - 1 for s in volume.shape), bool)
    for di in (0, 1):
        for dj in (0, 1):
            for dk in (0, 1):
                valid &= observed[
                    di : di + valid.shape[0], dj : dj + valid.shape[1], dk : dk + valid.shape[2]
                ]
    # inside (behind the surface) is tsdf < 0, so -tsdf > 0 is the "inside greater" convention
    values = -volume.tsdf.cpu().numpy()
    mesh = mesh_from_grid(values, volume.origin.cpu().numpy(), volume.voxel_size, 0.0, valid)
    if with_colors and len(mesh.vertices) > 0:
        points = torch.as_tensor(mesh.vertices, dtype=volume.tsdf.dtype, device=volume.tsdf.device)
        rgb = sample_colors(volume, points).clamp(0, 1).cpu().numpy()
        alpha = np.ones((len(rgb), 1))
        mesh.visual.vertex_colors = (np.concatenate([rgb, alpha], 1) * 255 + 0.5).astype(np.uint8)
    return mesh


def fuse_depth_maps(
    cameras: Cameras, depths: Tensor, rgbs: Tensor | None, aabb, config: TSDFConfig = TSDFConfig()
) -> trimesh.Trimesh:
    """Volume over aabb -> integrate all views -> mesh (colours when rgbs are given)."""
    volume = tsdf_volume(aabb, config, device=depths.device)
    integrate(volume, cameras, depths, rgbs, config.chunk)
    return tsdf_mesh(volume, with_colors=rgbs is not None)
