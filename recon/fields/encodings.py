"""Fixed input encodings (Mildenhall et al. 2020, eq. 4; Tancik et al. 2020)."""

from __future__ import annotations

import torch
from torch import Tensor


def positional_encoding(x: Tensor, num_bands: int = 10, include_input: bool = True) -> Tensor:
    """gamma(x) = [x, sin(b_0 x), .., sin(b_{L-1} x), cos(b_0 x), .., cos(b_{L-1} x)] per
    coordinate, b_j = 2^j pi, the identity first, then sin/cos per frequency: x (..., D) -> (..., D + 2 D L).

    The raw input comes first, then for each coordinate its L sines followed by its L cosines.
    Mildenhall et al. 2020 (NeRF), Sec. 5.1, eq. 4: L = 10 in 3D gives 3 + 3 * 2 * 10 = 63 dims;
    L = 4 for directions gives 27.
    """
    freqs = (2.0 ** torch.arange(num_bands, device=x.device, dtype=x.dtype)) * torch.pi  # (L,)
    xb = x[..., None] * freqs  # (..., D, L)
    enc = torch.cat([torch.sin(xb), torch.cos(xb)], dim=-1).flatten(start_dim=-2)  # (..., 2DL)
    return torch.cat([x, enc], dim=-1) if include_input else enc


def positional_encoding_dim(in_dim: int, num_bands: int, include_input: bool = True) -> int:
    """Output width of `positional_encoding`: D (if included) + 2 D L."""
    return in_dim * (2 * num_bands + int(include_input))
