"""Scene contraction for unbounded scenes (Barron et al. 2022, "Mip-NeRF 360", eq. 10):

    contract(x) = x                        if |x| <= 1
                  (2 - 1/|x|) x / |x|      otherwise,

which maps all of R^3 into the ball of radius 2, is continuous with continuous first derivative
at |x| = 1, and sends |x| -> infinity to |contract(x)| -> 2.
"""

from __future__ import annotations

import torch
from torch import Tensor


def contract(x: Tensor) -> Tensor:
    """mip-NeRF 360 contraction (L2 norm). x: (..., 3) -> (..., 3) with |out| < 2.

    The outside branch is evaluated at a norm clamped to >= 1, so neither branch produces
    inf/nan gradients that `torch.where` would otherwise propagate (x = 0, |x| = 1e30).
    Example: (3, 0, 0) -> (5/3, 0, 0).
    """
    norm = x.norm(dim=-1, keepdim=True)
    safe = norm.clamp_min(1.0)
    outside = (2.0 - 1.0 / safe) * (x / safe)
    return torch.where(norm <= 1.0, x, outside)


def normalize_to_box(x: Tensor, aabb: Tensor) -> Tensor:
    """Affine map of the box aabb (2, 3) onto [-1, 1]^3: x (..., 3) -> (..., 3)."""
    return 2.0 * (x - aabb[0]) / (aabb[1] - aabb[0]) - 1.0


def scene_to_unit_cube(x: Tensor, aabb: Tensor, unbounded: bool) -> Tensor:
    """Points in the world (normalized scene frame) -> [0, 1]^3, the domain of the grids.

    Bounded: the box aabb maps onto [0, 1]^3 (points outside are clamped by the caller's grid).
    Unbounded: the box maps onto [-1, 1]^3, is contracted into the radius-2 ball, then scaled so
    the ball's bounding cube [-2, 2]^3 becomes [0, 1]^3 (the box itself occupies [1/4, 3/4]^3).
    """
    y = normalize_to_box(x, aabb)
    if unbounded:
        return 0.25 * contract(y) + 0.5
    return 0.5 * y + 0.5


def uncontract(y: Tensor) -> Tensor:
    """The inverse of `contract` on the open ball |y| < 2: y for |y| <= 1, else
    y / (|y| (2 - |y|)) (|x| = 1 / (2 - |y|)); points at or beyond |y| = 2 give inf.
    Example: (5/3, 0, 0) -> (3, 0, 0)."""
    norm = y.norm(dim=-1, keepdim=True)
    safe = norm.clamp_min(1.0)
    outside = y / (safe * (2.0 - safe))
    return torch.where(norm <= 1.0, y, torch.where(norm < 2.0, outside, torch.inf))


def unit_cube_to_scene(u: Tensor, aabb: Tensor, unbounded: bool) -> Tensor:
    """The inverse of `scene_to_unit_cube`: [0, 1]^3 -> the normalized scene frame (N, 3); an
    unbounded scene's points outside the contraction's ball (|4 u - 2| >= 2) give inf."""
    y = 4.0 * u - 2.0 if unbounded else 2.0 * u - 1.0
    if unbounded:
        y = uncontract(y)
    return aabb[0] + (y + 1.0) * 0.5 * (aabb[1] - aabb[0])
