"""Projection, unprojection and ray generation (pixel centres at +0.5), batched over
leading dimensions and device-agnostic."""

from __future__ import annotations

import torch
from torch import Tensor

from recon.cameras.cameras import Cameras


def project_points(points_in_cam: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """Pinhole projection  lambda [u, v, 1]^T = K X_cam  (Hartley & Zisserman 2004, Sec. 6.1).

    points_in_cam: (..., 3); K: (..., 3, 3) broadcastable. Returns uv (..., 2) in pixels
    and depth (..., ) = Z along the optical axis.
    Worked example: f=800, c=(320, 240), X=(0.5, -0.3, 4) -> (420, 180).
    """
    z = points_in_cam[..., 2]
    xy = points_in_cam[..., :2] / z[..., None]
    u = K[..., 0, 0] * xy[..., 0] + K[..., 0, 1] * xy[..., 1] + K[..., 0, 2]
    v = K[..., 1, 1] * xy[..., 1] + K[..., 1, 2]
    return torch.stack([u, v], dim=-1), z


def unproject_pixels(uv: Tensor, depth: Tensor, K: Tensor) -> Tensor:
    """Inverse of `project_points`: pixels (..., 2) at depth Z (...,) -> points_in_cam (..., 3)."""
    y = (uv[..., 1] - K[..., 1, 2]) / K[..., 1, 1]
    x = (uv[..., 0] - K[..., 0, 2] - K[..., 0, 1] * y) / K[..., 0, 0]
    return torch.stack([x * depth, y * depth, depth], dim=-1)


def pixel_centers(width: int, height: int, device=None, dtype=torch.float32) -> Tensor:
    """(H, W, 2) pixel-centre coordinates (u, v) = (col + 0.5, row + 0.5)."""
    u = torch.arange(width, device=device, dtype=dtype) + 0.5
    v = torch.arange(height, device=device, dtype=dtype) + 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu, vv], dim=-1)


def rays_from_pixels(
    uv: Tensor, K: Tensor, world_from_cam: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """World-space rays through pixels.

    uv: (..., 2); K: (..., 3, 3); world_from_cam: (..., 4, 4), broadcastable.
    Returns origins (..., 3), unit directions (..., 3) and `z_per_t` (...,): the optical-axis
    depth gained per unit of ray length, so depth_z = t * z_per_t.
    """
    shape = torch.broadcast_shapes(uv.shape[:-1], K.shape[:-2])
    d_cam = unproject_pixels(uv.expand(*shape, 2), uv.new_ones(shape), K)  # z = 1 plane
    norm = d_cam.norm(dim=-1, keepdim=True)
    d_cam = d_cam / norm
    R = world_from_cam[..., :3, :3]
    directions = (R @ d_cam[..., None])[..., 0]
    origins = world_from_cam[..., :3, 3].expand_as(directions)
    return origins, directions, d_cam[..., 2]


def camera_rays(cameras: Cameras, index: int) -> tuple[Tensor, Tensor, Tensor]:
    """All rays of camera `index`: origins, directions (H, W, 3) and z_per_t (H, W)."""
    w, h = int(cameras.width[index]), int(cameras.height[index])
    uv = pixel_centers(w, h, device=cameras.device, dtype=cameras.K.dtype)
    return rays_from_pixels(uv, cameras.K[index], cameras.world_from_cam[index])
