"""The sample scene: a box, an ellipsoid and a tilted torus on a round plate, painted with a
random solid texture, lit by one directional light, seen by rings of pinhole cameras.

World frame: metres, z up. The texture is a function of the 3D surface point (a "solid"
texture), so the rasterizer needs no UV maps and every pixel sample gets the exact colour of
the surface point it sees: colour = albedo(x) * (ambient + (1 - ambient) max(0, n . l)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from torch import Tensor

from recon.cameras import Cameras
from recon.cameras.cameras import intrinsics_matrix
from recon.cameras.conventions import rotation_from_quat_wxyz
from recon.cameras.look_at import look_at
from recon.options import opt
from recon.synthetic.raster import front_facing, interpolate, rasterize

PART_NAMES = ("plate", "box", "ellipsoid", "torus")


@dataclass(frozen=True)
class SceneConfig:
    """Geometry, texture and light of the sample scene (lengths in metres, world z up)."""

    seed: int = opt(0, "seeds the texture's random colours and lattice orientations")
    plate_center: tuple[float, float, float] = opt(
        (0.3, -0.2, 0.3), "centre of the plate's top face"
    )
    # the 4 cm thick disk the objects stand on; it fills each view up to the image borders,
    # where features pin down a view's focal length (a smaller plate doubles SfM pose errors)
    plate_radius: float = 1.0
    coarse_cell: float = opt(0.09, "edge of the random-colour cells (~12 px at 1.9 m, f=250 px)")
    fine_cell: float = opt(
        0.035, "edge of the random-brightness cells that add corners inside them"
    )
    small_dot_cell: float = opt(0.07, "one dot of contrasting colour per cell: SIFT-sized blobs")
    large_dot_cell: float = opt(0.16, "a second, coarser layer of dots for the larger SIFT scales")
    light_direction: tuple[float, float, float] = opt((0.4, -0.3, 0.85), "towards the light")
    ambient: float = opt(0.6, "light on faces turned away, so their texture keeps its contrast")


@dataclass(frozen=True)
class SceneMesh:
    """The triangles of all parts in one indexed mesh, world frame."""

    vertices: Tensor  # (V, 3) float64 metres
    faces: Tensor  # (F, 3) int64 vertex indices, counter-clockwise seen from outside
    face_part: Tensor  # (F,) int64 index into PART_NAMES


@dataclass(frozen=True)
class SolidTexture:
    """Random tables behind the lattice-cell texture (T entries each)."""

    perm: Tensor  # (T,) int64 permutation used as a hash of integer cell coordinates
    colors: Tensor  # (T, 3) float64 random colours (saturation >= 0.45) for the coarse cells
    brightness: Tensor  # (T,) float64 random factors in [0.35, 1] for the fine cells
    dot_center: Tensor  # (T, 3) float64 in [0, 1]: where in its cell a dot sits
    dot_radius: Tensor  # (T,) float64 dot radius as a fraction of the cell edge
    rotations: Tensor  # (4, 3, 3) float64 orientations of the coarse, fine and two dot lattices


def _part_meshes(config: SceneConfig) -> list[trimesh.Trimesh]:
    """The four parts, in PART_NAMES order, placed in the world frame."""
    top = np.asarray(config.plate_center, dtype=np.float64)

    def placed(mesh: trimesh.Trimesh, x: float, y: float, yaw_deg: float) -> trimesh.Trimesh:
        mesh.apply_transform(
            trimesh.transformations.rotation_matrix(math.radians(yaw_deg), [0, 0, 1])
        )
        # Stand the part on the plate: its lowest point touches the plate's top face.
        mesh.apply_translation(top + [x, y, -mesh.bounds[0, 2]])
        return mesh

    plate = _disk(config.plate_radius, 0.04, rings=8, sections=128)
    plate.apply_translation(top)
    box = placed(trimesh.creation.box(extents=(0.40, 0.30, 0.34)), -0.30, 0.15, 25.0)
    ellipsoid = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    ellipsoid.apply_scale((0.20, 0.17, 0.24))
    ellipsoid = placed(ellipsoid, 0.28, 0.22, -30.0)
    torus = trimesh.creation.torus(0.20, 0.065, major_sections=96, minor_sections=32)
    torus.apply_transform(trimesh.transformations.rotation_matrix(math.radians(65.0), [1, 0, 0]))
    torus = placed(torus, 0.05, -0.34, 20.0)
    return [plate, box, ellipsoid, torus]


def _disk(radius: float, thickness: float, rings: int, sections: int) -> trimesh.Trimesh:
    """Closed disk, top face at z = 0, caps tessellated in concentric rings: small faces keep
    the rasterizer's bounding boxes tight (a fan of long slivers would cost ~30x more)."""
    a = 2.0 * np.pi * np.arange(sections) / sections
    r = radius * np.arange(1, rings + 1) / rings
    ring_xy = np.stack([np.outer(r, np.cos(a)), np.outer(r, np.sin(a))], -1).reshape(-1, 2)
    cap = np.concatenate([[[0.0, 0.0]], ring_xy])  # centre, then ring k section j at 1 + k S + j
    n = len(cap)
    j = np.arange(sections)
    ring = 1 + sections * np.arange(rings)[:, None]  # (rings, 1) first vertex of each ring
    here, there = ring + j, ring + (j + 1) % sections  # (rings, S): a vertex and its neighbour
    fan = np.stack([np.zeros(sections, np.int64), here[0], there[0]], -1)
    out_a = np.stack([here[:-1], here[1:], there[1:]], -1).reshape(-1, 3)
    out_b = np.stack([here[:-1], there[1:], there[:-1]], -1).reshape(-1, 3)
    top = np.concatenate([fan, out_a, out_b])
    bottom = top[:, ::-1] + n  # mirrored winding: faces down
    r0, r1 = here[-1], there[-1]
    side = np.concatenate([np.stack([r0, r0 + n, r1], -1), np.stack([r1, r0 + n, r1 + n], -1)])
    vertices = np.concatenate([np.c_[cap, np.zeros(n)], np.c_[cap, np.full(n, -thickness)]])
    return trimesh.Trimesh(vertices, np.concatenate([top, bottom, side]), process=False)


def build_scene(config: SceneConfig) -> SceneMesh:
    """The scene's triangles. The objects stand on the plate without touching each other."""
    parts = _part_meshes(config)
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    vertices = np.concatenate([p.vertices for p in parts])
    faces = np.concatenate([p.faces + o for p, o in zip(parts, offsets)])
    face_part = np.concatenate([np.full(len(p.faces), i) for i, p in enumerate(parts)])
    return SceneMesh(
        torch.as_tensor(vertices, dtype=torch.float64),
        torch.as_tensor(faces, dtype=torch.int64),
        torch.as_tensor(face_part, dtype=torch.int64),
    )


def face_normals(mesh: SceneMesh) -> Tensor:
    """n = (v1 - v0) x (v2 - v0) / |...| per face, (F, 3): outward for counter-clockwise faces."""
    v0, v1, v2 = mesh.vertices[mesh.faces].unbind(1)
    n = torch.linalg.cross(v1 - v0, v2 - v0)
    return n / n.norm(dim=-1, keepdim=True)


def make_texture(seed: int, size: int = 4096) -> SolidTexture:
    """Random tables of the solid texture, identical for identical seeds."""
    rng = np.random.default_rng(seed)
    perm = rng.permutation(size)
    hue = rng.uniform(0.0, 1.0, size)
    sat = rng.uniform(0.45, 1.0, size)
    val = rng.uniform(0.2, 1.0, size)  # SIFT sees grey levels: vary luminance, not just hue
    brightness = rng.choice([0.35, 0.7, 1.0], size)
    dot_center = rng.uniform(0.0, 1.0, (size, 3))
    dot_radius = rng.uniform(0.12, 0.32, size)
    q = rng.normal(size=(4, 4))  # random unit quaternions: the lattices align with no face
    return SolidTexture(
        torch.as_tensor(perm),
        torch.as_tensor(_hsv_to_rgb(hue, sat, val)),
        torch.as_tensor(brightness),
        torch.as_tensor(dot_center),
        torch.as_tensor(dot_radius),
        torch.as_tensor(rotation_from_quat_wxyz(q)),
    )


def _hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(N,) hue, saturation, value in [0, 1] -> (N, 3) RGB (the standard hexcone model)."""
    k = (np.array([5.0, 3.0, 1.0]) + 6.0 * h[:, None]) % 6.0
    return v[:, None] - v[:, None] * s[:, None] * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)


def _cell_hash(perm: Tensor, cells: Tensor, salt: Tensor) -> Tensor:
    """h = P[P[P[i + 61 salt] + j] + k] (indices mod T): a table index per integer cell (N, 3)."""
    T = len(perm)
    h = perm[torch.remainder(cells[:, 0] + 61 * salt, T)]
    h = perm[torch.remainder(h + cells[:, 1], T)]
    return perm[torch.remainder(h + cells[:, 2], T)]


def _lattice(
    texture: SolidTexture, local: Tensor, level: int, cell: float
) -> tuple[Tensor, Tensor]:
    """Point coordinates in cell units of lattice `level`: integer cell (N, 3) and the
    position inside it (N, 3) in [0, 1)."""
    x = local @ texture.rotations[level].T / cell
    cells = torch.floor(x)
    return cells.long(), x - cells


def _in_dot(texture: SolidTexture, cells: Tensor, inside: Tensor, salt: Tensor) -> Tensor:
    """(N,) bool: the point lies in its cell's ball |inside - c| < r, where c is kept r away
    from the cell walls so every ball lies within its own cell (no neighbour lookups)."""
    h = _cell_hash(texture.perm, cells, salt)
    r = texture.dot_radius[h]
    c = r[:, None] + texture.dot_center[h] * (1.0 - 2.0 * r[:, None])
    return (inside - c).norm(dim=-1) < r


def _contrasting(color: Tensor) -> Tensor:
    """A tint of `color` (N, 3) far away in luminance: darkened below 0.25 if it is bright,
    lifted above 0.75 if it is dark (SIFT works on grey levels)."""
    luminance = color @ torch.tensor([0.299, 0.587, 0.114], dtype=color.dtype, device=color.device)
    return torch.where(luminance[:, None] > 0.45, 0.25 * color, 0.75 + 0.25 * color)


def albedo(texture: SolidTexture, config: SceneConfig, points: Tensor, part: Tensor) -> Tensor:
    """Colour of surface points (N, 3) of parts (N,) -> (N, 3) in [0, 1]: the random colour of
    the coarse cell holding the point times the random brightness of its fine cell, then
    painted over with a contrasting colour inside the dots of two dot lattices.
    Each lattice is rotated randomly; `part` salts the hash so parts look different."""
    centre = torch.as_tensor(config.plate_center, dtype=points.dtype, device=points.device)
    local = points - centre
    n_parts = len(PART_NAMES)
    coarse, _ = _lattice(texture, local, 0, config.coarse_cell)
    fine, _ = _lattice(texture, local, 1, config.fine_cell)
    color = texture.colors[_cell_hash(texture.perm, coarse, part)]
    color = color * texture.brightness[_cell_hash(texture.perm, fine, part + n_parts)][:, None]
    for level, cell in ((2, config.small_dot_cell), (3, config.large_dot_cell)):
        cells, inside = _lattice(texture, local, level, cell)
        dot = _in_dot(texture, cells, inside, part + level * n_parts)
        color = torch.where(dot[:, None], _contrasting(color), color)
    return color


def render_view(
    mesh: SceneMesh,
    texture: SolidTexture,
    config: SceneConfig,
    cameras: Cameras,
    index: int,
    supersample: int = 3,
) -> tuple[Tensor, Tensor]:
    """Anti-aliased RGBA (H, W, 4) in [0, 1] and z-depth (H, W) of camera `index`.

    Every pixel averages supersample^2 samples: alpha is the covered fraction, RGB the mean
    colour of the covered samples (straight alpha; white where nothing is covered). Depth is
    the exact z of the surface at the pixel centre (0 if none), the middle sample of an odd
    supersampling grid.
    """
    if supersample % 2 != 1:
        raise ValueError("supersample must be odd so one sample sits at each pixel centre")
    s, w, h = supersample, int(cameras.width[index]), int(cameras.height[index])
    fine = cameras[index].scaled(float(s))
    front = torch.nonzero(front_facing(mesh.vertices, mesh.faces, fine.cam_from_world[0]))[:, 0]
    faces = mesh.faces[front]  # every part is closed, so back faces are hidden anyway
    frags = rasterize(mesh.vertices, faces, fine.K[0], fine.cam_from_world[0], w * s, h * s)
    hit = frags.mask
    face = front[frags.face_index[hit]]
    points = interpolate(frags, faces, mesh.vertices)[hit]
    light = torch.tensor(config.light_direction, dtype=torch.float64)
    lambert = (face_normals(mesh)[face] @ (light / light.norm())).clamp_min(0.0)
    shade = config.ambient + (1.0 - config.ambient) * lambert
    color = torch.zeros(h * s, w * s, 3, dtype=torch.float64)  # premultiplied by coverage
    color[hit] = albedo(texture, config, points, mesh.face_part[face]) * shade[:, None]
    premultiplied = color.view(h, s, w, s, 3).mean((1, 3))
    alpha = hit.double().view(h, s, w, s).mean((1, 3))
    rgb = torch.where(alpha[..., None] > 0, premultiplied / alpha.clamp_min(1e-12)[..., None], 1.0)
    return torch.cat([rgb, alpha[..., None]], -1), frags.depth[s // 2 :: s, s // 2 :: s]


def ring_cameras(
    target: tuple[float, float, float],
    radius: float,
    elevations_deg: tuple[float, ...],
    views_per_ring: int,
    focal: float,
    width: int,
    height: int,
) -> Cameras:
    """Rings of cameras at distance `radius` around `target` (world z up), all looking at it.

    Ring r of R sits at elevation elevations_deg[r]; its azimuths are 2 pi (k + r / R) / n, so
    the rings interleave. The principal point is the image centre.
    """
    target_t = torch.tensor(target, dtype=torch.float64)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    poses = []
    for ring, elevation in enumerate(elevations_deg):
        e = math.radians(elevation)
        for k in range(views_per_ring):
            a = 2.0 * math.pi * (k + ring / len(elevations_deg)) / views_per_ring
            direction = [math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]
            offset = torch.tensor(direction, dtype=torch.float64)
            poses.append(look_at(target_t + radius * offset, target_t, up))
    C = len(poses)
    full = torch.full((C,), 1.0, dtype=torch.float64)
    K = intrinsics_matrix(focal * full, focal * full, 0.5 * width * full, 0.5 * height * full)
    size = torch.ones(C, dtype=torch.int64)
    return Cameras(K, torch.stack(poses), width * size, height * size)


def spiral_cameras(
    target: tuple[float, float, float],
    count: int,
    turns: float,
    elevations_deg: tuple[float, float],
    radii: tuple[float, float],
    focal: float,
    width: int,
    height: int,
) -> Cameras:
    """`count` cameras along a closed path around `target` (world z up), all looking at it:
    a photographer walking `turns` times around an object, raising the camera from
    elevations_deg[0] to [1] by the middle of the walk and lowering it back, while stepping
    out to radii[1] in the first half and in to radii[0] in the second. With t = i / count,
    view i is at azimuth 2 pi turns t, elevation e0 + (e1 - e0) (1 - cos(2 pi t)) / 2 and
    distance (r0 + r1) / 2 + (r1 - r0) sin(2 pi t) / 2 from the target; the sine (odd about
    t = 1/2, where the elevation is even) keeps views a whole number of turns apart distinct.
    The principal point is the image centre.
    """
    target_t = torch.tensor(target, dtype=torch.float64)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    poses = []
    for i in range(count):
        t = i / count
        a = 2.0 * math.pi * turns * t
        e = math.radians(
            elevations_deg[0]
            + (elevations_deg[1] - elevations_deg[0]) * 0.5 * (1 - math.cos(2 * math.pi * t))
        )
        r = 0.5 * (radii[0] + radii[1]) + 0.5 * (radii[1] - radii[0]) * math.sin(2 * math.pi * t)
        direction = [math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]
        eye = target_t + r * torch.tensor(direction, dtype=torch.float64)
        poses.append(look_at(eye, target_t, up))
    full = torch.full((count,), 1.0, dtype=torch.float64)
    K = intrinsics_matrix(focal * full, focal * full, 0.5 * width * full, 0.5 * height * full)
    size = torch.ones(count, dtype=torch.int64)
    return Cameras(K, torch.stack(poses), width * size, height * size)


def scene_trimesh(mesh: SceneMesh, texture: SolidTexture, config: SceneConfig) -> trimesh.Trimesh:
    """The ground-truth mesh for export, vertex colours = albedo at the vertices (for viewing)."""
    part = torch.zeros(len(mesh.vertices), dtype=torch.int64)
    part[mesh.faces.flatten()] = mesh.face_part.repeat_interleave(3)
    colors = albedo(texture, config, mesh.vertices, part)
    rgba = np.concatenate([np.round(colors.numpy() * 255), np.full((len(colors), 1), 255)], 1)
    return trimesh.Trimesh(
        mesh.vertices.numpy(),
        mesh.faces.numpy(),
        vertex_colors=rgba.astype(np.uint8),
        process=False,
    )
