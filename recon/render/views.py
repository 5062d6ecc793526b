"""Rendering a view at an output resolution that may be coarser than the camera it is rendered
with: the render is area-downsampled to the output size, so a model trained at a finer level
is judged on the same area-averaged pixels as the photos of the coarser pyramid level."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from recon.cameras import Cameras
from recon.io.images import resize_area


def area_downsample_render(out: dict[str, Tensor], width: int, height: int) -> dict[str, Tensor]:
    """rgb (H, W, 3), depth (H, W), acc (H, W) -> the same at (height, width) by area resampling.

    rgb and acc are area averages; depth is the acc-weighted average sum(acc z) / sum(acc) over
    each output pixel's footprint (the expected depth of what covers it; 0 where nothing does).
    Example: a 2x2 block with acc (1, 1, 0, 0) and depths (2, 4, -, -) -> acc 0.5, depth 3.
    """
    h, w = out["rgb"].shape[:2]
    if (w, h) == (width, height):
        return out

    def area(x: Tensor) -> np.ndarray:
        return resize_area(np.ascontiguousarray(x.detach().float().cpu().numpy()), width, height)

    acc = area(out["acc"])
    weighted = area(out["depth"] * out["acc"])
    depth = np.where(acc > 1e-6, weighted / np.maximum(acc, 1e-6), 0.0)
    to = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float32)).to(out["rgb"].device)
    return {"rgb": to(area(out["rgb"])), "depth": to(depth), "acc": to(acc)}


@torch.no_grad()
def render_view(model, camera: Cameras, width: int, height: int) -> dict[str, Tensor]:
    """Render the single camera `camera` and area-downsample to width x height if it is finer."""
    return area_downsample_render(model.render(camera), width, height)
