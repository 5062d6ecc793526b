"""Rendering finer than the training views sampled: every splat keeps at least the screen-space
footprint its finest training view gave it.

A 3D Gaussian splatting model is fitted through a low-pass dilation of 0.3 px^2 added to
every projected covariance (the reference implementation of Kerbl et al. 2023; the
screen-space low-pass filter of EWA splatting, Zwicker et al. 2001), in the training views'
pixels. Nothing constrains a Gaussian's shape below that footprint: a splat fitted as a sub-pixel point is, to the photos, a blob of
variance 0.3 px^2. Rendered with the same 0.3 px^2 at 4x the training size, the blob shrinks 16x
in area and the image breaks into dots and dark gaps (the zoom-in artefact of Yu et al. 2024,
"Mip-Splatting"). Mip-Splatting's cure is to train with a 3D filter; this is the render-time
half of it that needs no retraining: the dilation is held fixed in world units instead of in
output pixels. A training camera at depth z with focal f samples the scene every z / f; the
finest sampling of Gaussian i over the training views is T_i (Mip-Splatting Eq. 8,
`mip_filter.sampling_intervals`), where its footprint was 0.3 px^2 = 0.3 T_i^2 in world units.
A render with focal f at depth z therefore dilates by

    d_i = 0.3 max(1, (f T_i / z)^2)  px^2,

which is 0.3 in every view no finer than the training ones (the training views themselves
render unchanged) and grows as the square of the magnification beyond them. An antialiased
model (opacity times sqrt(det Sigma / det(Sigma + d I))) keeps its compensation with the new d,
so a splat keeps its integral; a plain model keeps its peak opacity, as its dilation did.
"""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from recon.gaussians.projection import DILATION

# the per-axis radius gsplat bins by (`gsplat_glue`): ceil(3.33 sigma)
GSPLAT_SIGMAS = 3.33


def footprint_dilation(
    depths: Tensor, intervals: Tensor, focal: float, dilation: float = DILATION
) -> Tensor:
    """depths z (G,), finest training sampling intervals T (G,), focal f px -> (G,) the dilation
    d = dilation max(1, (f T / z)^2) px^2. Example: T = 0.01, z = 2, f = 400 -> f T / z = 2,
    d = 1.2 px^2; f = 100 (coarser than the training view) -> 0.3."""
    ratio = focal * intervals.to(depths) / depths.clamp_min(1e-12)
    return dilation * torch.clamp(ratio * ratio, min=1.0)


def with_training_footprint(splats, intervals: Tensor, focal: float, antialiased: bool):
    """`ProjectedSplats` projected with the 0.3 px^2 dilation -> the same with each splat's
    dilation `footprint_dilation` instead: conics, radii and (antialiased) opacities follow.
    Splats whose dilation stays 0.3 keep their values bit for bit; culled ones stay culled.

    The conic (A, B, C) is the inverse of Sigma' = Sigma + 0.3 I, so Sigma' = [[C, -B], [-B, A]]
    / (A C - B^2) and the new Sigma'' = Sigma' + (d - 0.3) I; radius ceil(3 sqrt(lambda_max)).
    An antialiased opacity o sqrt(det Sigma / det Sigma') becomes o sqrt(det Sigma /
    det Sigma''), a factor sqrt(det Sigma' / det Sigma'')."""
    d = footprint_dilation(splats.depths, intervals, focal)
    grow = (d - DILATION) * (splats.radii > 0)
    changed = grow > 0
    if not bool(changed.any()):
        return splats
    A, B, C = splats.conics.unbind(-1)
    det_conic = (A * C - B * B).clamp_min(1e-30)
    sxx, sxy, syy = C / det_conic, -B / det_conic, A / det_conic
    nxx, nyy = sxx + grow, syy + grow
    det_old = sxx * syy - sxy * sxy
    det_new = nxx * nyy - sxy * sxy
    conics = torch.stack([nyy / det_new, -sxy / det_new, nxx / det_new], -1)
    conics = torch.where(changed[:, None], conics, splats.conics)
    mid, gap = 0.5 * (nxx + nyy), torch.sqrt((0.25 * (nxx - nyy) ** 2 + sxy * sxy).clamp_min(0))
    radii = torch.ceil(3.0 * torch.sqrt(mid + gap)).to(splats.radii.dtype)
    radii = torch.where(changed, torch.maximum(radii, splats.radii), splats.radii)
    opacities = splats.opacities
    if antialiased:
        opacities = torch.where(changed, opacities * torch.sqrt(det_old / det_new), opacities)
    radii_xy = splats.radii_xy
    if radii_xy is not None:
        axes = torch.stack([nxx, nyy], -1).clamp_min(0).sqrt()
        grown = torch.ceil(GSPLAT_SIGMAS * axes).to(radii_xy.dtype)
        radii_xy = torch.where(changed[:, None], torch.maximum(grown, radii_xy), radii_xy)
    return replace(splats, conics=conics, radii=radii, opacities=opacities, radii_xy=radii_xy)
