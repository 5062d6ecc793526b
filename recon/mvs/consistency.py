"""Multi-view geometric consistency of depth maps (the forward-backward reprojection check of
Schönberger et al. 2016, Sec. 4.4, and Yao et al. 2018, MVSNet Sec. 4.2): a depth survives
when enough other views' depth maps put the same surface point there.

Reference pixel u with depth z -> point X (world) -> projected into view s at u_s -> view s's
depth z_s there lifts it to X_s -> X_s projected back into the reference at u'. The views
agree when |u' - u| < max_reprojection (pixels) and |z(X_s) - z| < max_depth_ratio z.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from recon.cameras.cameras import Cameras
from recon.cameras.rays import pixel_centers, project_points, unproject_pixels


def _transform(points: Tensor, m: Tensor) -> Tensor:
    return points @ m[:3, :3].T + m[:3, 3]


def depth_to_world(depth: Tensor, K: Tensor, world_from_cam: Tensor) -> Tensor:
    """(H, W) z-depth of a camera -> (H, W, 3) points in the world (pixel centres at +0.5)."""
    H, W = depth.shape
    uv = pixel_centers(W, H, device=depth.device, dtype=depth.dtype)
    return _transform(unproject_pixels(uv, depth, K), world_from_cam)


def consistent_views(
    depths: Tensor,
    cameras: Cameras,
    reference: int,
    max_reprojection: float = 1.0,
    max_depth_ratio: float = 0.01,
) -> tuple[Tensor, Tensor]:
    """For every pixel of view `reference`: how many other views agree with its depth, and the
    mean of the agreeing points (its own included), in the world.

    depths: (C, H, W) z-depths of all views (0 = none); cameras: the C views (all H x W).
    Returns count (H, W) int and points (H, W, 3): the fused point of every pixel.
    """
    C, H, W = depths.shape
    depth = depths[reference]
    uv = pixel_centers(W, H, device=depths.device, dtype=depths.dtype)
    points = depth_to_world(depth, cameras.K[reference], cameras.world_from_cam[reference])
    count = torch.zeros(H, W, dtype=torch.int64, device=depths.device)
    total = points.clone()
    for s in range(C):
        if s == reference:
            continue
        uv_s, z_s = project_points(_transform(points, cameras.cam_from_world[s]), cameras.K[s])
        grid = torch.stack([uv_s[..., 0] / W * 2 - 1, uv_s[..., 1] / H * 2 - 1], dim=-1)
        depth_s = F.grid_sample(
            depths[s][None, None], grid[None], mode="nearest", align_corners=False
        )[0, 0]
        back_world = _transform(
            unproject_pixels(uv_s, depth_s, cameras.K[s]), cameras.world_from_cam[s]
        )
        uv_back, z_back = project_points(
            _transform(back_world, cameras.cam_from_world[reference]), cameras.K[reference]
        )
        agree = (grid.abs() <= 1).all(-1) & (z_s > 0) & (depth_s > 0) & (depth > 0)
        agree &= (uv_back - uv).norm(dim=-1) < max_reprojection
        agree &= (z_back - depth).abs() < max_depth_ratio * depth
        count += agree
        total += torch.where(agree[..., None], back_world, 0.0)
    return count, total / (count + 1)[..., None].to(total.dtype)
