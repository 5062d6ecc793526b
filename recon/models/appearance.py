"""Per-image appearance: a learnt affine colour correction of each training photo.

Photos of one capture differ in exposure and white balance (auto-exposure, clouds, a phone's
tone mapping); a scene model asked to reproduce every photo exactly bakes those differences
into view-dependent colour and floaters. As in the per-image affine colour transforms of
gsplat/nerfstudio's appearance options (and the per-image latent appearance of Martin-Brualla
et al. 2021, NeRF in the Wild, section 4.1, reduced to its simplest global form), the rendered
colour of training image i is corrected before the loss:

    c' = A_i c + b_i,   [A_i | b_i] = [I | 0] + D_i - (1/C) sum_j D_j,

with D_i (3, 4) learnt and zero at the start. Subtracting the mean deviation fixes the gauge:
the scene could otherwise drift in colour while every correction drifts the opposite way, and
the mean correction over the training images is the identity by construction.

A view that is not a training image (a held-out photo, a camera path) has no correction of its
own, and nothing is ever fitted to a test image. It takes the inverse-distance-weighted mean of
the corrections of the `NEIGHBOURS` training cameras closest to it (camera centre distance plus
half the angle gap of the viewing directions, `neighbour_correction`): a phone's auto-exposure
follows what the camera looks at, so nearby training photos predict it (the identity instead
would score a held-out photo against an exposure no training photo had).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from recon.cameras import Cameras

NEIGHBOURS = 3  # training cameras whose corrections a novel view borrows
DIRECTION_WEIGHT = 0.5  # scene units per unit of (1 - cos) between viewing directions


def affine_colour(rgb: Tensor, correction: Tensor) -> Tensor:
    """c' = A c + b for every pixel: rgb (..., 3), correction (3, 4) = [A | b] -> (..., 3).
    Example: A = 2 I, b = (0.1, 0, 0) maps (0.2, 0.3, 0.4) to (0.5, 0.6, 0.8)."""
    return rgb @ correction[:, :3].T + correction[:, 3]


def centred_corrections(deltas: Tensor) -> Tensor:
    """[I | 0] + D_i - mean_j D_j for deltas D (C, 3, 4) -> (C, 3, 4); their mean is [I | 0]."""
    identity = torch.eye(3, 4, dtype=deltas.dtype, device=deltas.device)
    return identity + deltas - deltas.mean(0, keepdim=True)


def neighbour_correction(
    corrections: Tensor,
    centers: Tensor,
    directions: Tensor,
    center: Tensor,
    direction: Tensor,
    k: int = NEIGHBOURS,
) -> Tensor:
    """The correction (3, 4) of a view at `center` (3,) looking along unit `direction` (3,):
    sum_i w_i [A_i | b_i] over the k training cameras nearest in d_i = |o_i - o| +
    DIRECTION_WEIGHT (1 - v_i . v), with w_i proportional to 1 / d_i (a training camera itself,
    d = 0, gets its own correction). corrections (C, 3, 4), centers, directions (C, 3).
    Example: two cameras at distances 1 and 3 with gains 1.2 and 0.8 (k = 2) -> weights 3/4 and
    1/4, gain 1.1."""
    d = (centers - center).norm(dim=-1) + DIRECTION_WEIGHT * (1 - directions @ direction)
    d, idx = torch.topk(d, min(k, len(d)), largest=False)
    if d[0] <= 1e-9:
        return corrections[idx[0]]
    w = 1 / d
    return (w[:, None, None] * corrections[idx]).sum(0) / w.sum()


class AppearanceCorrection(nn.Module):
    """The learnt corrections of C training images (the trainer's Adam at lr `lr` fits them),
    and where those cameras are (for views that are not training images). A model that meets
    its training cameras only at the first step starts with C = 0 and calls `reset`."""

    def __init__(self, num_images: int, lr: float):
        super().__init__()
        self.lr = lr
        self.resize(num_images)

    def resize(self, num_images: int) -> None:
        """Identity corrections (and blank camera anchors) for `num_images` images: the shapes
        a saved state is loaded into."""
        device = self.deltas.device if hasattr(self, "deltas") else None
        self.deltas = nn.Parameter(torch.zeros(num_images, 3, 4, device=device))
        self.register_buffer("centers", torch.zeros(num_images, 3, device=device))
        self.register_buffer("directions", torch.zeros(num_images, 3, device=device))

    def reset(self, cameras: Cameras) -> None:
        """Identity corrections for the training cameras, anchored at their centres and viewing
        directions (the optical axes)."""
        self.resize(len(cameras))
        world_from_cam = cameras.world_from_cam.to(self.deltas.device)
        self.centers.copy_(world_from_cam[:, :3, 3])
        self.directions.copy_(world_from_cam[:, :3, 2])

    def forward(self, rgb: Tensor, image: int) -> Tensor:
        """The rendered rgb (..., 3) of training image `image`, corrected."""
        return affine_colour(rgb, centred_corrections(self.deltas)[image])

    @torch.no_grad()
    def for_camera(self, rgb: Tensor, camera: Cameras) -> Tensor:
        """The rendered rgb (..., 3) of any single camera, corrected by `neighbour_correction`."""
        world_from_cam = camera.world_from_cam[0].to(self.deltas)
        corr = neighbour_correction(
            centred_corrections(self.deltas),
            self.centers,
            self.directions,
            world_from_cam[:3, 3],
            world_from_cam[:3, 2],
        )
        return affine_colour(rgb, corr)

    @torch.no_grad()
    def spread(self) -> dict[str, float]:
        """How far the corrections are from the identity: the largest |A - I| entry and |b|."""
        corr = centred_corrections(self.deltas) - torch.eye(3, 4, device=self.deltas.device)
        return {
            "appearance_max_gain_dev": float(corr[..., :3].abs().max()),
            "appearance_max_offset": float(corr[..., 3].abs().max()),
        }
