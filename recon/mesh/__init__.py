"""Meshes from trained scenes: marching cubes on a density field, TSDF fusion of rendered depth
(any method, incl. 3dgs), then cleanup, transform to original units and export."""

from recon.mesh.cleanup import (
    keep_largest_components,
    mesh_stats,
    remove_small_components,
    transform_mesh,
    write_mesh,
)
from recon.mesh.marching_cubes import (
    choose_density_threshold,
    extract_density_mesh,
    mesh_from_grid,
)
from recon.mesh.tsdf import TSDFConfig, fuse_depth_maps, integrate, tsdf_mesh, tsdf_volume

__all__ = [
    "TSDFConfig",
    "choose_density_threshold",
    "extract_density_mesh",
    "fuse_depth_maps",
    "integrate",
    "keep_largest_components",
    "mesh_from_grid",
    "mesh_stats",
    "remove_small_components",
    "transform_mesh",
    "tsdf_mesh",
    "tsdf_volume",
    "write_mesh",
]
