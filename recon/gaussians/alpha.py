"""Limits of alpha compositing shared by the rasterizer, its packed torch version and its
reference twin (Kerbl et al. 2023, Sec. 6 and the reference CUDA rasterizer)."""

ALPHA_MAX = 0.99  # keeps 1 - alpha away from 0 so the backward can divide by it
ALPHA_MIN = 1.0 / 255.0  # contributions below one 8-bit level are skipped
T_MIN = 1e-4  # early termination: a pixel stops before T would fall below this
SLACK = 1e-3  # relative widening of the alpha >= ALPHA_MIN ellipse used to skip pixels and tiles
