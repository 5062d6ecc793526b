"""Synthetic Gaussians and cameras for the 3dgs tests and speed benchmarks: a sphere shell of
G Gaussians seen from an orbit."""

from __future__ import annotations

import math

import torch

from recon.cameras import Cameras
from recon.cameras.look_at import look_at


def shell_gaussians(G: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """G Gaussians on a sphere shell with random orientations, colours and opacities."""
    gen = torch.Generator().manual_seed(seed)
    d = torch.randn(G, 3, generator=gen)
    means = d / d.norm(dim=-1, keepdim=True) * (0.8 + 0.05 * torch.rand(G, 1, generator=gen))
    spacing = math.sqrt(4 * math.pi * 0.8**2 / G)  # mean distance between neighbours
    return {
        "means": means,
        "quats": torch.randn(G, 4, generator=gen),
        "log_scales": torch.log(spacing * (0.5 + torch.rand(G, 3, generator=gen))),
        "opacity_logits": torch.randn(G, generator=gen) + 1.0,
        "sh_dc": torch.randn(G, 1, 3, generator=gen) * 0.5,
        "sh_rest": torch.randn(G, 15, 3, generator=gen) * 0.05,
    }


def orbit_cameras(n: int, size: int, radius: float = 3.0) -> Cameras:
    """n cameras on a circle around the origin, looking at it (OpenCV axes, world z up)."""
    a = 2 * math.pi * torch.arange(n, dtype=torch.float64) / n
    eyes = torch.stack([radius * torch.cos(a), radius * torch.sin(a), torch.full_like(a, 0.5)], -1)
    cfw = look_at(eyes, torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0]))
    K = (
        torch.tensor(
            [[1.2 * size, 0, size / 2], [0, 1.2 * size, size / 2], [0, 0, 1]], dtype=torch.float64
        )
        .expand(n, 3, 3)
        .clone()
    )
    wh = torch.full((n,), size)
    return Cameras(K, cfw, wh, wh.clone())
