"""3D Gaussian splatting (seed, "3D Gaussian Splatting"): EWA projection, a tile rasterizer with
a numba CPU fast path and a pure-torch twin, adaptive density control and splat PLY export."""
