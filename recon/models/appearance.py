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
the mean correction over the training images is the identity by construction. Held-out views
have no fitted correction - nothing is ever fitted to a test image - and are rendered with the
identity, which is therefore exactly the mean correction of the training images.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


def affine_colour(rgb: Tensor, correction: Tensor) -> Tensor:
    """c' = A c + b for every pixel: rgb (..., 3), correction (3, 4) = [A | b] -> (..., 3).
    Example: A = 2 I, b = (0.1, 0, 0) maps (0.2, 0.3, 0.4) to (0.5, 0.6, 0.8)."""
    return rgb @ correction[:, :3].T + correction[:, 3]


def centred_corrections(deltas: Tensor) -> Tensor:
    """[I | 0] + D_i - mean_j D_j for deltas D (C, 3, 4) -> (C, 3, 4); their mean is [I | 0]."""
    identity = torch.eye(3, 4, dtype=deltas.dtype, device=deltas.device)
    return identity + deltas - deltas.mean(0, keepdim=True)


class AppearanceCorrection(nn.Module):
    """The learnt corrections of C training images, with their own Adam (lr `lr`). A model that
    learns the number of its training images only at the first step starts with C = 0 and
    calls `reset`."""

    def __init__(self, num_images: int, lr: float):
        super().__init__()
        self.lr = lr
        self.reset(num_images)

    def reset(self, num_images: int) -> None:
        """Identity corrections for `num_images` images and a fresh optimizer."""
        device = self.deltas.device if hasattr(self, "deltas") else None
        self.deltas = nn.Parameter(torch.zeros(num_images, 3, 4, device=device))
        self.optimizer = torch.optim.Adam([self.deltas], lr=self.lr, eps=1e-15)

    def forward(self, rgb: Tensor, image: int) -> Tensor:
        """The rendered rgb (..., 3) of training image `image`, corrected."""
        return affine_colour(rgb, centred_corrections(self.deltas)[image])

    @torch.no_grad()
    def spread(self) -> dict[str, float]:
        """How far the corrections are from the identity: the largest |A - I| entry and |b|."""
        corr = centred_corrections(self.deltas) - torch.eye(3, 4, device=self.deltas.device)
        return {"appearance_max_gain_dev": float(corr[..., :3].abs().max()),
                "appearance_max_offset": float(corr[..., 3].abs().max())}
