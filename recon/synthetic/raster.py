"""An exact z-buffer triangle rasterizer for ground-truth renders (OpenCV cameras, pixel
centres at +0.5). Clarity first: float64 throughout, one sample per pixel centre; callers
supersample by rasterizing at a multiple of the resolution (`Cameras.scaled`).

Per sample, a triangle's screen-space barycentrics l_i are affine in (u, v), and so is 1/z
under a pinhole, which gives the perspective-correct weights and the exact plane depth:

    1/z = sum_i l_i / z_i,      b_i = (l_i / z_i) * z.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from recon.cameras.rays import project_points

# Barycentric margin of the inside test: samples this close outside an edge still count.
EDGE_TOLERANCE = 1e-10


@dataclass(frozen=True)
class Fragments:
    """The nearest surface at every pixel sample of one (H, W) image."""

    face_index: Tensor  # (H, W) int64 face id, -1 where the sample sees no surface
    barycentric: Tensor  # (H, W, 3) perspective-correct weights of the face's vertices, 0 if none
    depth: Tensor  # (H, W) float64 z-depth along the optical axis, 0 if none

    @property
    def mask(self) -> Tensor:
        """(H, W) bool: the sample sees a surface."""
        return self.face_index >= 0


def transform_points(a_from_b: Tensor, points_in_b: Tensor) -> Tensor:
    """x_a = R x_b + t for (4, 4) `a_from_b` and (N, 3) points."""
    return points_in_b @ a_from_b[:3, :3].T + a_from_b[:3, 3]


def _faces_in_front(z: Tensor, near: float) -> Tensor:
    """(F,) faces with every vertex beyond `near`; faces crossing the near plane are refused
    because the pinhole projection of a vertex behind the camera is meaningless (no clipping)."""
    in_front = z > near
    straddling = in_front.any(-1) & ~in_front.all(-1)
    if straddling.any():
        raise ValueError(f"{int(straddling.sum())} faces cross the near plane z={near}")
    return in_front.all(-1)


def _sample_boxes(uv: Tensor, width: int, height: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """First column/row and counts of the pixel centres (j + 0.5) inside each face's bbox.

    uv: (F, 3, 2). Returns x0, y0, nx, ny, each (F,) int64 (counts clamped at 0)."""
    # A margin of 1e-6 px keeps a sample that rounding puts just outside the box (a vertex
    # exactly on a pixel centre); the inside test then decides.
    lo = torch.ceil(uv.amin(1) - 0.5 - 1e-6).clamp_min(0)
    hi = torch.floor(uv.amax(1) - 0.5 + 1e-6)
    hi = torch.minimum(hi, torch.tensor([width - 1, height - 1], dtype=hi.dtype, device=hi.device))
    n = (hi - lo + 1).clamp_min(0).long()
    lo = lo.long()
    return lo[:, 0], lo[:, 1], n[:, 0], n[:, 1]


def _perspective_weights(uv: Tensor, z: Tensor) -> Tensor:
    """Affine maps W (F, 3, 3) with w = W [u, v, 1]^T = l / z, the screen barycentrics l of the
    pixel (u, v) divided by the vertex depths: w_i >= 0 inside, 1/z = sum w, b = w z.

    With vertices a, b, c: l_a = ((b - p) x (c - p)) / ((b - a) x (c - a)), and cyclically.
    Faces seen edge-on (zero screen area) get W = 0, i.e. they cover nothing.
    """
    a, b, c = uv.unbind(1)  # (F, 2) each
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    rows = []
    for s, t in ((b, c), (c, a), (a, b)):  # l = ((s - p) x (t - p)) / area, affine in p
        rows.append(
            torch.stack(
                [s[:, 1] - t[:, 1], t[:, 0] - s[:, 0], s[:, 0] * t[:, 1] - s[:, 1] * t[:, 0]], -1
            )
        )
    scale = torch.where(area != 0, 1.0 / area, 0.0)[:, None, None] / z[:, :, None]
    return torch.stack(rows, 1) * scale


def _cover_faces(uv: Tensor, z: Tensor, width: int, height: int, near: float) -> tuple[Tensor, ...]:
    """All (sample, face) pairs where a pixel centre falls inside a face (edges included).

    uv: (F, 3, 2) projected vertices; z: (F, 3) their depths. Returns flat pixel index,
    local face index, depth and perspective-correct barycentrics (M, 3) of the M hits.
    """
    x0, y0, nx, ny = _sample_boxes(uv, width, height)
    counts = nx * ny
    face = torch.repeat_interleave(torch.arange(len(uv), device=uv.device), counts)
    offset = torch.arange(len(face), device=uv.device) - (torch.cumsum(counts, 0) - counts)[face]
    col, row = x0[face] + offset % nx[face], y0[face] + offset // nx[face]
    p = torch.stack([col + 0.5, row + 0.5, torch.ones_like(col)], -1).to(uv.dtype)
    w = (_perspective_weights(uv, z)[face] @ p[:, :, None])[:, :, 0]  # (M, 3)
    depth = 1.0 / w.sum(-1)
    bary = w * depth[:, None]
    # Edges are inclusive, with a margin for rounding, so a sample on a shared edge or vertex
    # is never lost: it hits both faces at the same depth and the z-buffer keeps one.
    # W = 0 faces give depth = inf and fail.
    hit = (bary >= -EDGE_TOLERANCE).all(-1) & (depth > near) & torch.isfinite(depth)
    return (row * width + col)[hit], face[hit], depth[hit], bary[hit]


def _z_buffer(pixel: Tensor, depth: Tensor, n_pixels: int) -> Tensor:
    """Index of the nearest hit per pixel, (n_pixels,) with -1 where nothing was hit; ties in
    depth go to the earliest hit (the lowest face index, since hits are ordered by face)."""
    zmin = torch.full((n_pixels,), torch.inf, dtype=depth.dtype, device=depth.device)
    zmin = zmin.scatter_reduce(0, pixel, depth, "amin")
    nearest = depth == zmin[pixel]
    big = len(depth)
    first = torch.full((n_pixels,), big, dtype=torch.long, device=depth.device)
    hit_index = torch.arange(big, device=depth.device)
    first = first.scatter_reduce(0, pixel[nearest], hit_index[nearest], "amin")
    return torch.where(first == big, -1, first)


def rasterize(
    points_in_world: Tensor,
    faces: Tensor,
    K: Tensor,
    cam_from_world: Tensor,
    width: int,
    height: int,
    near: float = 1e-3,
    max_candidates: int = 1 << 22,
) -> Fragments:
    """Nearest face, perspective-correct barycentrics and z-depth at each pixel centre.

    points_in_world: (V, 3) vertices; faces: (F, 3) int64; K: (3, 3); cam_from_world: (4, 4).
    Candidate (sample, face) pairs are enumerated per face bounding box, at most
    `max_candidates` at a time, so memory stays bounded for large faces.
    """
    dev = points_in_world.device
    points_in_cam = transform_points(cam_from_world.double(), points_in_world.double())
    uv, z = project_points(points_in_cam[faces], K.double())  # (F, 3, 2), (F, 3)
    keep = torch.nonzero(_faces_in_front(z, near))[:, 0]
    _, _, nx, ny = _sample_boxes(uv[keep], width, height)
    area = nx * ny
    keep, area = keep[area > 0], area[area > 0]
    cost = torch.cumsum(area, 0)
    hits, start = [], 0
    while start < len(keep):
        budget = cost[start] - area[start] + max_candidates
        stop = max(int(torch.searchsorted(cost, budget, right=True)), start + 1)
        ids = keep[start:stop]
        pixel, local, depth, bary = _cover_faces(uv[ids], z[ids], width, height, near)
        hits.append((pixel, ids[local], depth, bary))
        start = stop
    if not hits:
        return Fragments(
            torch.full((height, width), -1, dtype=torch.long, device=dev),
            torch.zeros((height, width, 3), dtype=torch.float64, device=dev),
            torch.zeros((height, width), dtype=torch.float64, device=dev),
        )
    pixel, face, depth, bary = (torch.cat(h) for h in zip(*hits))
    best = _z_buffer(pixel, depth, width * height)
    found, best = best >= 0, best.clamp_min(0)
    return Fragments(
        torch.where(found, face[best], -1).view(height, width),
        torch.where(found[:, None], bary[best], 0.0).view(height, width, 3),
        torch.where(found, depth[best], 0.0).view(height, width),
    )


def front_facing(points_in_world: Tensor, faces: Tensor, cam_from_world: Tensor) -> Tensor:
    """(F,) bool: faces whose counter-clockwise normal n points at the camera, (v0 - o) . n < 0.

    Back faces of a closed, outward-wound mesh are never the nearest surface, so dropping them
    before `rasterize` leaves the image unchanged and halves the work.
    """
    v0, v1, v2 = points_in_world.double()[faces].unbind(1)
    n = torch.linalg.cross(v1 - v0, v2 - v0)
    R, t = cam_from_world.double()[:3, :3], cam_from_world.double()[:3, 3]
    origin = -R.T @ t  # camera centre in the world
    return ((v0 - origin) * n).sum(-1) < 0


def interpolate(fragments: Fragments, faces: Tensor, attributes: Tensor) -> Tensor:
    """a(sample) = sum_i b_i a_{face[i]}: per-vertex (V, D) attributes -> (H, W, D), 0 if none."""
    face = faces[fragments.face_index.clamp_min(0)]  # (H, W, 3)
    values = (fragments.barycentric[..., None] * attributes.double()[face]).sum(-2)
    return torch.where(fragments.mask[..., None], values, 0.0)


def rasterize_reference(
    points_in_world: Tensor,
    faces: Tensor,
    K: Tensor,
    cam_from_world: Tensor,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """Brute-force twin of `rasterize`: intersect every pixel-centre ray with every face
    (Moller-Trumbore) and keep the nearest. Returns face_index (H, W) and z-depth (H, W).
    O(H W F) memory: for tests on tiny images only."""
    points_in_cam = transform_points(cam_from_world.double(), points_in_world.double())
    v0, v1, v2 = points_in_cam[faces].unbind(1)  # (F, 3) each
    u = torch.arange(width, dtype=torch.float64) + 0.5
    v = torch.arange(height, dtype=torch.float64) + 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    K = K.double()
    y = (vv - K[1, 2]) / K[1, 1]
    x = (uu - K[0, 2] - K[0, 1] * y) / K[0, 0]
    d = torch.stack([x, y, torch.ones_like(x)], -1).reshape(-1, 1, 3)  # z = 1: t is z-depth
    e1, e2 = v1 - v0, v2 - v0
    pvec = torch.linalg.cross(d.expand(-1, len(faces), 3), e2.expand(len(d), -1, 3))
    det = (e1 * pvec).sum(-1)
    s = -v0  # ray origin is the camera centre
    a = (s * pvec).sum(-1) / det
    q = torch.linalg.cross(s.expand(len(d), -1, 3), e1.expand(len(d), -1, 3))
    b = (d * q).sum(-1) / det
    t = (e2 * q).sum(-1) / det
    hit = (det != 0) & (a >= 0) & (b >= 0) & (a + b <= 1) & (t > 0)
    t = torch.where(hit, t, torch.inf)
    depth, face = t.min(-1)
    found = torch.isfinite(depth)
    face = torch.where(found, face, -1).view(height, width)
    return face, torch.where(found, depth, 0.0).view(height, width)
