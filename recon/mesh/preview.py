"""A picture of a mesh a person can look at: the mesh seen from one camera, shaded by its
normals under a light at the camera (headlight Lambert: I = ambient + (1 - ambient) |n . v|),
on a white background. Exact z-buffer rasterization (`recon.synthetic.raster`)."""

from __future__ import annotations

import numpy as np
import torch
import trimesh

from recon.synthetic.raster import interpolate, rasterize

AMBIENT = 0.25
BASE_GREY = 0.85


def shaded_view(
    mesh: trimesh.Trimesh,
    K: np.ndarray,
    cam_from_world: np.ndarray,
    width: int,
    height: int,
    normals: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W, 3) uint8: the mesh (vertices in the camera's world frame) seen by the pinhole
    camera K (3, 3), cam_from_world (4, 4), shaded by per-vertex `normals` (V, 3) when given
    (the field's), else by the faces' normals. Pixels that see no surface are white.
    Example: a sphere seen head-on is brightest (I = 1 x 0.85) at its centre, AMBIENT x 0.85
    at its rim."""
    vertices = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float64)
    faces = torch.as_tensor(np.asarray(mesh.faces), dtype=torch.long)
    image = np.ones((height, width, 3))
    if len(faces) == 0:
        return (image * 255).astype(np.uint8)
    c2w = torch.as_tensor(np.asarray(cam_from_world, np.float64))
    frag = rasterize(
        vertices, faces, torch.as_tensor(np.asarray(K, np.float64)), c2w, width, height
    )
    if normals is not None:
        n = interpolate(frag, faces, torch.as_tensor(np.asarray(normals, np.float64)))
    else:
        face_n = torch.tensor(np.array(mesh.face_normals, np.float64))
        n = face_n[frag.face_index.clamp_min(0)]
    n = torch.nn.functional.normalize(n, dim=-1)
    # the view direction at each pixel, in the world: R^T K^-1 (u, v, 1)
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float64) + 0.5,
        torch.arange(width, dtype=torch.float64) + 0.5,
        indexing="ij",
    )
    rays = (
        torch.stack([u, v, torch.ones_like(u)], -1)
        @ torch.linalg.inv(torch.as_tensor(np.asarray(K, np.float64))).T
    )
    view = torch.nn.functional.normalize(rays @ c2w[:3, :3], dim=-1)
    shade = AMBIENT + (1 - AMBIENT) * (n * view).sum(-1).abs()
    hit = frag.mask.numpy()
    image[hit] = (BASE_GREY * shade.numpy()[hit])[:, None]
    return (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
