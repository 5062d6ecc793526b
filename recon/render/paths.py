"""Camera paths for videos: orbit, spiral and interpolation, as `cam_from_world` (P, 4, 4)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from recon.cameras.cameras import invert_rigid
from recon.cameras.look_at import look_at


def orbit_path(centers: Tensor, target: Tensor, frames: int) -> Tensor:
    """A circle about the +z axis through `target`, at the training cameras' mean radius and height."""
    rel = centers - target
    radius = rel[:, :2].norm(dim=-1).mean()
    height = rel[:, 2].mean()
    angles = torch.linspace(0, 2 * math.pi, frames + 1, dtype=centers.dtype)[:-1]
    eye = (
        torch.stack(
            [radius * torch.cos(angles), radius * torch.sin(angles), height.expand(frames)], dim=-1
        )
        + target
    )
    return look_at(eye, target, torch.tensor([0.0, 0.0, 1.0], dtype=centers.dtype))


def spiral_path(world_from_cam: Tensor, target: Tensor, frames: int, rots: float = 2.0) -> Tensor:
    """A forward-facing spiral around the mean camera (LLFF style), radius from the camera spread."""
    c = world_from_cam[:, :3, 3]
    mean_c = c.mean(0)
    R = world_from_cam[:, :3, :3].mean(0)
    right, down = R[:, 0], R[:, 1]
    spread = (c - mean_c).abs().quantile(0.9, dim=0).norm().clamp_min(1e-3)
    t = torch.linspace(0, 2 * math.pi * rots, frames + 1, dtype=c.dtype)[:-1]
    eye = (
        mean_c
        + spread * (torch.cos(t)[:, None] * right + torch.sin(t)[:, None] * down)
        + 0.5
        * spread
        * torch.sin(t / rots)[:, None]
        * torch.nn.functional.normalize(target - mean_c, dim=0)
    )
    return look_at(eye, target, -down)


def _slerp_rot(Ra: Tensor, Rb: Tensor, s: float) -> Tensor:
    """Geodesic interpolation between rotations via the matrix log of Ra^T Rb (axis-angle)."""
    D = Ra.T @ Rb
    cos = ((torch.trace(D) - 1) / 2).clamp(-1, 1)
    angle = torch.arccos(cos)
    if angle < 1e-8:
        return Ra
    axis = torch.stack([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]]) / (
        2 * torch.sin(angle)
    )
    a = angle * s
    Kx = torch.tensor(
        [[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=Ra.dtype
    )
    return Ra @ (torch.eye(3, dtype=Ra.dtype) + torch.sin(a) * Kx + (1 - torch.cos(a)) * Kx @ Kx)


def interpolate_path(world_from_cam: Tensor, frames: int) -> Tensor:
    """Piecewise geodesic interpolation through the given cameras (in order)."""
    n = world_from_cam.shape[0]
    out = []
    for k in range(frames):
        u = k / max(frames - 1, 1) * (n - 1)
        i = min(int(u), n - 2) if n > 1 else 0
        s = u - i if n > 1 else 0.0
        a, b = world_from_cam[i], world_from_cam[min(i + 1, n - 1)]
        m = torch.eye(4, dtype=a.dtype)
        m[:3, :3] = _slerp_rot(a[:3, :3], b[:3, :3], s)
        m[:3, 3] = (1 - s) * a[:3, 3] + s * b[:3, 3]
        out.append(m)
    return invert_rigid(torch.stack(out))
