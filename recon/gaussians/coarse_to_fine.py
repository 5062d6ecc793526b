"""Coarse-to-fine training of 3D Gaussian splatting: the first steps fit area-downsampled
targets at a fraction of the working resolution, then the resolution doubles on a schedule that
ends at the working resolution (the resolution scheduling of Chen et al. 2025, DashGaussian,
section 3.2, simplified to doubling at fixed step intervals).

Early steps only need the coarse image structure, which a low resolution carries at a
fraction of the rasterization cost; the time saved buys more steps at the full working
resolution. Densification statistics stay consistent across a change of resolution because
they are kept in NDC units: for a Gaussian covering n of the image's P pixels, the loss gradient
per pixel of mean displacement scales as (n / P) / sigma_px, and n / P is the same at every
resolution while sigma_px shrinks with it, so dL/d mu_px grows by the downscale factor f and
dL/d mu_ndc = dL/d mu_px * (W / 2) does not change (`densify.accumulate`); screen radii are
compared relative to the image size too. (That holds for structured residuals, what
densification is for; residuals that are pixel noise cancel less over fewer, larger pixels under
an L1 loss, so a coarse level can read somewhat higher. The coarse levels are short.)

Off by default (`c2f_factor` 1): on a CPU at a few hundred pixels a side it does not pay at
equal wall time. On fox at 269 x 478 for 10 minutes the coarse levels saved 34 s over the first
500 steps, and every later step was ~5 % slower (the Gaussians densified against quarter-size
targets stay large on screen): the same number of steps in the end and the same quality.
"""

from __future__ import annotations

MIN_SIDE = 64  # a coarse level keeps at least this many pixels on the image's shorter side


def c2f_factor(step: int, start_factor: int, interval: int, short_side: int = 1 << 30) -> int:
    """The downscale of the training targets at `step`: `start_factor` for the first `interval`
    steps, halved after every further `interval` steps, and 1 once it gets there (1 when
    `start_factor` <= 1 or `interval` <= 0: no coarse-to-fine). Never so coarse that an image's
    `short_side` falls below `MIN_SIDE` pixels (small working images skip the coarsest levels).
    Example: start 4, interval 250 -> steps 0-249 at 1/4, 250-499 at 1/2, 500 on at full size;
    with a 200 px shorter side, steps 0-249 at 1/2 (1/4 would leave 50 px)."""
    if start_factor <= 1 or interval <= 0:
        return 1
    factor = max(1, start_factor >> (step // interval))
    while factor > 1 and short_side // factor < MIN_SIDE:
        factor //= 2
    return factor
