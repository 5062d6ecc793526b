"""A shaded picture of a mesh seen from a camera: a z-buffered triangle rasterizer (numba, one
thread) with a head-light Lambert shade, for the report and the geometry benchmark. No texture:
the shade shows the shape (a flat-shaded face is as bright as it faces the camera), and vertex
colours, when the mesh has them, tint it.

Pixel (u, v) covers [u, u + 1) x [v, v + 1) and is sampled at its centre (u + 0.5, v + 0.5), the
convention of the rest of recon; K maps camera coordinates to those pixel coordinates.
"""

from __future__ import annotations

import numba
import numpy as np

AMBIENT = 0.15  # share of the light that reaches a face seen edge-on
BACKGROUND = 255  # white


@numba.njit(cache=True)
def _rasterize(uv, depth, faces, shade, colours, image, zbuf):  # pragma: no cover - numba
    H, W = zbuf.shape
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        if depth[a] <= 0 or depth[b] <= 0 or depth[c] <= 0:
            continue  # a face crossing the camera plane is left out (previews look from outside)
        x0, y0 = uv[a, 0], uv[a, 1]
        x1, y1 = uv[b, 0], uv[b, 1]
        x2, y2 = uv[c, 0], uv[c, 1]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area == 0.0:
            continue
        u_lo = max(int(np.floor(min(x0, x1, x2) - 0.5)), 0)
        u_hi = min(int(np.ceil(max(x0, x1, x2) - 0.5)), W - 1)
        v_lo = max(int(np.floor(min(y0, y1, y2) - 0.5)), 0)
        v_hi = min(int(np.ceil(max(y0, y1, y2) - 0.5)), H - 1)
        for v in range(v_lo, v_hi + 1):
            py = v + 0.5
            for u in range(u_lo, u_hi + 1):
                px = u + 0.5
                w0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) / area
                w1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) / area
                w2 = 1.0 - w0 - w1
                if w0 < 0 or w1 < 0 or w2 < 0:
                    continue
                # perspective-correct depth: 1/z is affine in screen space
                z = 1.0 / (w0 / depth[a] + w1 / depth[b] + w2 / depth[c])
                if z < zbuf[v, u]:
                    zbuf[v, u] = z
                    for ch in range(3):
                        col = w0 * colours[a, ch] + w1 * colours[b, ch] + w2 * colours[c, ch]
                        image[v, u, ch] = min(255.0, shade[f] * col)


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit normals (F, 3) of the faces (right-handed: (b - a) x (c - a)); 0 for degenerate ones."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def shade_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    K: np.ndarray,
    cam_from_world: np.ndarray,
    width: int,
    height: int,
    colours: np.ndarray | None = None,
    vertex_normals: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The mesh (V, 3) world points, (F, 3) vertex indices, optional (V, 3) colours in [0, 1],
    seen by a pinhole camera K (3, 3), cam_from_world (4, 4) -> (H, W, 3) uint8 picture on white
    and (H, W) depth (inf where no face). A face is lit by a light at the camera, two-sided:
    brightness AMBIENT + (1 - AMBIENT) |n . d| with d the unit ray to the face's centre. With
    `vertex_normals` (V, 3) (a field's gradient, world frame) that brightness is taken at each
    vertex (d the ray to the vertex) and interpolated across the faces (Gouraud 1971)."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64).reshape(-1, 3)
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    cam = V @ R.T + t
    z = cam[:, 2]
    uvw = cam @ np.asarray(K, np.float64).T
    uv = uvw[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None]
    tint = 255.0 * (np.full((len(V), 3), 0.8) if colours is None else np.clip(colours, 0, 1))
    if vertex_normals is None:
        normals = face_normals(cam, F)
        centres = cam[F].mean(1)
        rays = centres / np.maximum(np.linalg.norm(centres, axis=1, keepdims=True), 1e-12)
        shade = AMBIENT + (1 - AMBIENT) * np.abs((normals * rays).sum(1))
    else:
        n = np.asarray(vertex_normals, np.float64) @ R.T  # directions turn with R only
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        rays = cam / np.maximum(np.linalg.norm(cam, axis=1, keepdims=True), 1e-12)
        tint = tint * (AMBIENT + (1 - AMBIENT) * np.abs((n * rays).sum(1)))[:, None]
        shade = np.ones(len(F))
    image = np.full((height, width, 3), float(BACKGROUND))
    zbuf = np.full((height, width), np.inf)
    _rasterize(uv, z, F, shade, np.ascontiguousarray(tint, np.float64), image, zbuf)
    return np.rint(image).astype(np.uint8), zbuf


def preview_views(num_views: int, count: int) -> list[int]:
    """`count` evenly spaced positions among `num_views` training views (all if fewer)."""
    if num_views <= count:
        return list(range(num_views))
    return [round(k * num_views / count) for k in range(count)]
