"""How much each Gaussian adds to the training images: its blending weights summed over every
pixel of every view, C_i = sum_views sum_p T_i(p) alpha_i(p) (the "global significance" of
LightGaussian, Fan et al. 2023, Sec. 3.1, without its volume factor), and pruning by it.

The rasterizer's backward already computes dF/df_i = sum_p T_i alpha_i for the composited
feature F; rendering the feature f_i = 1 and taking that gradient with dL/dF = 1 gives C_i for a
view with no new kernel. Since sum_i T_i alpha_i = 1 - T_final per pixel, sum_i C_i = the sum
over pixels of 1 - T_final (the identity the tests check).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor

from recon.cameras import Cameras
from recon.gaussians.render import project_splats, rasterize_splats


def view_contributions(
    gaussians: Mapping[str, Tensor],
    camera: Cameras,
    sh_degree: int,
    near: float,
    antialiased: bool = False,
) -> Tensor:
    """sum_p T_i(p) alpha_i(p) over the pixels of the single camera `camera`: (G,)."""
    detached = {k: v.detach() for k, v in gaussians.items()}
    with torch.no_grad():
        s = project_splats(detached, camera, sh_degree, near, antialiased)
    ones = s.colors.new_ones(len(s.opacities), 1).requires_grad_()
    with torch.enable_grad():
        image, _ = rasterize_splats(s, ones)
        (weights,) = torch.autograd.grad(image.sum(), ones)
    return weights[:, 0]


def contributions(
    gaussians: Mapping[str, Tensor],
    cameras: Cameras,
    sh_degree: int,
    near: float,
    antialiased: bool = False,
) -> Tensor:
    """C_i summed over the views `cameras`: (G,), float64, on the Gaussians' device."""
    means = gaussians["means"]
    total = torch.zeros(len(means), dtype=torch.float64, device=means.device)
    for view in range(len(cameras)):
        weights = view_contributions(gaussians, cameras[view], sh_degree, near, antialiased)
        total += weights.double()
    return total


def least_contributing(scores: Tensor, fraction: float) -> Tensor:
    """Mask (G,) of the floor(fraction G) lowest scores (ties broken by index).
    Example: scores (3, 1, 2, 0), fraction 0.5 -> (False, True, False, True)."""
    drop = torch.zeros(len(scores), dtype=torch.bool, device=scores.device)
    count = int(fraction * len(scores))
    drop[torch.argsort(scores, stable=True)[:count]] = True
    return drop
