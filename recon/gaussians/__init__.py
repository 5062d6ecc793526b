"""3D Gaussian splatting (Kerbl et al. 2023): EWA projection, a tile rasterizer with
a numba CPU fast path and a pure-torch twin, adaptive density control and splat PLY export."""
