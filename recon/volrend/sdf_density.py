"""Signed distance to volume density, so an SDF renders through the same quadrature as every
other volume method.

VolSDF (Yariv et al. 2021, "Volume Rendering of Neural Implicit Surfaces", eq. 2-3) is the one
used: sigma(x) = alpha Psi_beta(-d(x)) with Psi_beta the CDF of a zero-mean Laplace
distribution of scale beta and alpha = 1 / beta. Inside the surface (d < 0) sigma tends to
1 / beta, outside it decays as exp(-d / beta) / (2 beta): as beta -> 0 the density becomes a step
at the zero level set and the expected depth of a ray the distance to the surface.

NeuS (Wang et al. 2021, "NeuS", eq. 13) takes the discrete opacity of an interval from the
logistic CDF Phi_s of the SDF at its ends instead; `neus_alpha` is kept as the twin the tests
compare VolSDF's limiting behaviour with (both put a ray's weight at the surface when the
sharpness grows).
"""

from __future__ import annotations

import torch
from torch import Tensor


def laplace_cdf(s: Tensor, beta: Tensor | float) -> Tensor:
    """Psi_beta(s): 0.5 exp(s / beta) for s <= 0, 1 - 0.5 exp(-s / beta) for s > 0; written with
    expm1 of a non-positive argument so neither branch overflows.
    Example: beta 0.1 -> Psi(0) = 0.5, Psi(-0.1) = 0.5 / e = 0.18394, Psi(0.1) = 0.81606."""
    e = 0.5 * torch.exp(-s.abs() / beta)
    return torch.where(s <= 0, e, 1.0 - e)


def volsdf_density(sdf: Tensor, beta: Tensor | float) -> Tensor:
    """sigma = Psi_beta(-sdf) / beta (Yariv et al. 2021, eq. 2-3 with alpha = 1 / beta).
    sdf: (...,) signed distances (negative inside) -> (...,) densities >= 0."""
    return laplace_cdf(-sdf, beta) / beta


def neus_alpha(sdf_start: Tensor, sdf_end: Tensor, s: Tensor | float) -> Tensor:
    """NeuS's discrete opacity of an interval from the SDF at its two ends (Wang et al. 2021,
    eq. 13): alpha = max((Phi_s(f_start) - Phi_s(f_end)) / Phi_s(f_start), 0), Phi_s the
    logistic sigmoid of s f."""
    cdf_start, cdf_end = torch.sigmoid(s * sdf_start), torch.sigmoid(s * sdf_end)
    return ((cdf_start - cdf_end) / cdf_start.clamp_min(1e-12)).clamp_min(0.0)
