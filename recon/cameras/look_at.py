"""Cameras aimed at a point: the one `look_at` of the package."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn.functional import normalize


def look_at(eye: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """OpenCV cam_from_world (..., 4, 4) of cameras at `eye` (..., 3) whose optical axis (+z)
    points at `target` ((3,) or (..., 3)) and whose image up (-y) is as close to `up` as the
    view allows: z = target - eye, x (right) = z x up, y (down) = z x x, all unit length.
    Looking straight along `up`, world x serves as the reference instead."""
    z = normalize(target - eye, dim=-1)
    x = torch.linalg.cross(z, up.to(z.dtype).expand_as(z), dim=-1)
    parallel = x.norm(dim=-1, keepdim=True) < 1e-6
    if parallel.any():
        world_x = torch.tensor([1.0, 0.0, 0.0], dtype=z.dtype, device=z.device).expand_as(z)
        x = torch.where(parallel, torch.linalg.cross(z, world_x, dim=-1), x)
    x = normalize(x, dim=-1)
    y = torch.linalg.cross(z, x, dim=-1)
    R = torch.stack([x, y, z], dim=-2)  # rows: the camera axes in world coordinates
    cam_from_world = torch.zeros(*z.shape[:-1], 4, 4, dtype=z.dtype, device=z.device)
    cam_from_world[..., :3, :3] = R
    cam_from_world[..., :3, 3] = -(R @ eye.to(z.dtype)[..., None])[..., 0]
    cam_from_world[..., 3, 3] = 1.0
    return cam_from_world
