"""Mesh post-processing: drop floaters (small connected components), report counts, map a
mesh from the normalized scene box back to original units, write PLY / OBJ / GLB."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from recon.io.atomic import atomic_path

MESH_FORMATS = (".ply", ".obj", ".glb")


def component_labels(mesh: trimesh.Trimesh) -> np.ndarray:
    """(F,) label of the edge-connected component of each face, 0 = the most faces."""
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, len(mesh.faces))
    counts = np.bincount(labels)
    rank = np.empty_like(counts)
    rank[np.argsort(-counts, kind="stable")] = np.arange(len(counts))
    return rank[labels]


def _keep_faces(mesh: trimesh.Trimesh, keep: np.ndarray) -> trimesh.Trimesh:
    out = mesh.copy()
    out.update_faces(keep)
    out.remove_unreferenced_vertices()
    return out


def keep_largest_components(mesh: trimesh.Trimesh, n: int = 1) -> trimesh.Trimesh:
    """The n components with the most faces (the scene, without floaters)."""
    if len(mesh.faces) == 0:
        return mesh.copy()
    return _keep_faces(mesh, component_labels(mesh) < n)


def remove_small_components(
    mesh: trimesh.Trimesh, min_face_fraction: float = 0.01
) -> trimesh.Trimesh:
    """Drop components with fewer than min_face_fraction of all faces (the largest is kept)."""
    if len(mesh.faces) == 0:
        return mesh.copy()
    labels = component_labels(mesh)
    counts = np.bincount(labels)
    big = counts >= min_face_fraction * len(mesh.faces)
    big[0] = True
    return _keep_faces(mesh, big[labels])


def in_view(points: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray, size) -> np.ndarray:
    """(N,) bool: the points (N, 3) project inside a camera's image (width, height) in front of
    it (OpenCV pinhole: x_cam = [R | t] x, (u, v) = K x_cam / z, pixels [0, W) x [0, H))."""
    x = points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    z = x[:, 2]
    uv = x @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = uv[:, 0] / z, uv[:, 1] / z
    return (z > 0) & (u >= 0) & (u < size[0]) & (v >= 0) & (v < size[1])


def keep_seen_components(
    mesh: trimesh.Trimesh, K: np.ndarray, cam_from_world: np.ndarray, sizes: np.ndarray
) -> trimesh.Trimesh:
    """Drop the components no camera sees: none of their vertices projects inside any of the
    images (K (C, 3, 3), cam_from_world (C, 4, 4) or (C, 3, 4), sizes (C, 2) width, height).
    What a level set holds beyond every view (the box's corners, the back of the volume) is
    not what the photos show."""
    if len(mesh.faces) == 0:
        return mesh.copy()
    vertices = np.asarray(mesh.vertices, np.float64)
    seen_vertex = np.zeros(len(vertices), bool)
    for k, m, wh in zip(K, cam_from_world, sizes):
        seen_vertex |= in_view(vertices, np.asarray(k, np.float64), np.asarray(m, np.float64), wh)
    labels = component_labels(mesh)
    seen = np.zeros(labels.max() + 1, bool)
    seen[labels[seen_vertex[mesh.faces].any(axis=1)]] = True
    return _keep_faces(mesh, seen[labels])


def visible_faces(
    mesh: trimesh.Trimesh,
    K: np.ndarray,
    cam_from_world: np.ndarray,
    sizes: np.ndarray,
    tolerance: float,
) -> np.ndarray:
    """(F,) bool: the faces some camera sees. A face is seen when its centroid projects inside
    an image, in front of the camera, no more than `tolerance` (world units, along the optical
    axis) behind the nearest surface the z-buffer of the whole mesh holds at that pixel. The
    back sheet of a density shell (marching cubes around a surface of some thickness) and
    whatever the level set encloses are behind the front sheet from every camera."""
    from recon.mesh.preview import shade_mesh  # the z-buffer rasterizer

    vertices = np.asarray(mesh.vertices, np.float64)
    faces = np.asarray(mesh.faces, np.int64)
    centroids = vertices[faces].mean(axis=1)
    seen = np.zeros(len(faces), bool)
    for k, m, (w, h) in zip(K, cam_from_world, np.asarray(sizes, np.int64)):
        k, m = np.asarray(k, np.float64), np.asarray(m, np.float64)
        _, zbuf = shade_mesh(vertices, faces, k, m, int(w), int(h))
        x = centroids @ m[:3, :3].T + m[:3, 3]  # x_cam = R x + t, (u, v) = K x_cam / z
        z = x[:, 2]
        uv = x @ k.T
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = np.floor(uv[:, 0] / z), np.floor(uv[:, 1] / z)
        inside = np.flatnonzero((z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h))
        ui, vi = u[inside].astype(np.int64), v[inside].astype(np.int64)
        seen[inside[z[inside] <= zbuf[vi, ui] + tolerance]] = True
    return seen


def keep_visible_faces(
    mesh: trimesh.Trimesh,
    K: np.ndarray,
    cam_from_world: np.ndarray,
    sizes: np.ndarray,
    tolerance: float,
) -> trimesh.Trimesh:
    """The mesh without the faces no camera sees (`visible_faces`)."""
    if len(mesh.faces) == 0:
        return mesh.copy()
    return _keep_faces(mesh, visible_faces(mesh, K, cam_from_world, sizes, tolerance))


def mesh_stats(mesh: trimesh.Trimesh) -> dict:
    """Vertex / face / component counts, watertightness, area (and volume when closed)."""
    n_components = int(component_labels(mesh).max() + 1) if len(mesh.faces) else 0
    stats = {
        "vertices": len(mesh.vertices),
        "faces": len(mesh.faces),
        "components": n_components,
        "watertight": bool(mesh.is_watertight) if len(mesh.faces) else False,
        "area": float(mesh.area),
    }
    if stats["watertight"]:
        stats["volume"] = float(mesh.volume)
    return stats


def transform_mesh(
    mesh: trimesh.Trimesh, scale: float, rotation: np.ndarray, translation: np.ndarray
) -> trimesh.Trimesh:
    """x_orig = s R x + t for every vertex (normalized scene -> original units).

    Requires s > 0 and R a proper rotation, so face winding (outward normals) is preserved.
    Example: s = 2, R = I, t = (1, 0, 0) maps the vertex (1, 1, 1) to (3, 2, 2).
    """
    R = np.asarray(rotation, np.float64)
    if scale <= 0 or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError("transform_mesh: need scale > 0 and a proper rotation matrix")
    out = mesh.copy()
    out.vertices = scale * np.asarray(mesh.vertices, np.float64) @ R.T + np.asarray(translation)
    return out


def mesh_to_original_units(mesh: trimesh.Trimesh, scene_from_world) -> trimesh.Trimesh:
    """A mesh in the normalized scene frame moved back to the original units:
    x_scene = s R x_world + t  ->  x_world = (1/s) R^T x_scene - R^T t / s."""
    sim = scene_from_world
    return transform_mesh(mesh, 1.0 / sim.scale, sim.R.T, -sim.R.T @ sim.t / sim.scale)


def write_mesh(mesh: trimesh.Trimesh, path: Path) -> Path:
    """Write PLY (binary), OBJ or GLB by suffix, atomically; vertex colours included."""
    path = Path(path)
    if path.suffix.lower() not in MESH_FORMATS:
        raise ValueError(
            f"write_mesh: unsupported format {path.suffix!r}, use one of {MESH_FORMATS}"
        )
    with atomic_path(path) as tmp:
        mesh.export(tmp)
    return path
