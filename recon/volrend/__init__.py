"""ONE rendering core: the volume methods (nerf, ngp, plenoxel) composite through it, and so
does the 3DGS reference rasterizer (`alpha_compositing`), which the numba kernels are tested
against.

Pure functions over sample intervals, padded (R, S) or packed (N,) + ray_indices:
  volrend      - alpha, exclusive transmittance, weights, compositing (Max 1995; Mildenhall et al. 2020, eq. 3).
  samplers     - ray/box intersection, stratified and inverse-CDF (hierarchical) sampling.
  occupancy    - occupancy bitfield, marching with empty-space skipping, early termination.
  contraction  - mip-NeRF 360 scene contraction for unbounded scenes.
"""

from recon.volrend.contraction import (
    contract,
    normalize_to_box,
    scene_to_unit_cube,
    unit_cube_to_scene,
)
from recon.volrend.occupancy import (
    OccupancyGrid,
    march_intervals,
    march_terminated,
    terminated_mask,
)
from recon.volrend.samplers import (
    intervals_from_points,
    merge_points,
    ray_aabb_intersect,
    sample_pdf,
    spaced_intervals,
    stratified_intervals,
)
from recon.volrend.volrend import (
    VolumeRender,
    accumulate_along_rays,
    alpha_compositing,
    exclusive_cumsum,
    render_transmittance,
    render_weights,
    render_with_fn,
    surface_depth,
    volume_render,
)

__all__ = [
    "OccupancyGrid",
    "VolumeRender",
    "accumulate_along_rays",
    "alpha_compositing",
    "contract",
    "exclusive_cumsum",
    "intervals_from_points",
    "march_intervals",
    "march_terminated",
    "merge_points",
    "normalize_to_box",
    "ray_aabb_intersect",
    "render_transmittance",
    "render_weights",
    "render_with_fn",
    "sample_pdf",
    "scene_to_unit_cube",
    "spaced_intervals",
    "stratified_intervals",
    "surface_depth",
    "terminated_mask",
    "unit_cube_to_scene",
    "volume_render",
]
