"""The `mesh` stage: a trained run -> WS/runs/<run>/mesh/mesh.<fmt> in ORIGINAL scene units.

auto = TSDF fusion of the rendered depth of the training views, for every method: on
sample_data it beats marching cubes on the density wherever both exist (240 s runs, F-score at
tau = 1 %: ngp 0.979 against 0.944, plenoxel 0.971 against 0.956; bench/results/mesh_sample.md),
and on the walnut ring ngp's marching-cubes mesh came out empty. `--method marching-cubes`
extracts a level set of the density (nerf/ngp/plenoxel), keeping the faces a camera sees.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch

from recon.io.images import write_png
from recon.mesh.cleanup import (
    keep_seen_components,
    keep_visible_faces,
    mesh_stats,
    mesh_to_original_units,
    remove_small_components,
    write_mesh,
)
from recon.mesh.marching_cubes import (
    choose_density_threshold,
    extract_density_mesh,
    soft_field_threshold,
)
from recon.mesh.preview import preview_views, shade_mesh
from recon.mesh.tsdf import TSDFConfig, fuse_depth_maps
from recon.models.registry import pick_device
from recon.options import opt
from recon.train.resolution import downscale_for_max_side, trained_resolution
from recon.workspace import Workspace, WorkspaceError, atomic_write_json
from recon.workspace.runs import load_run


@dataclass(frozen=True)
class MeshConfig:
    method: str = opt(
        "auto",
        "auto: marching cubes on the zero level set of a signed distance field (sdf), TSDF "
        "fusion of rendered depth for every other method (the geometry benchmark's best); "
        "marching-cubes: a level set of the density (nerf/ngp/plenoxel)",
        choices=("auto", "marching-cubes", "tsdf"),
    )
    resolution: int = opt(
        256, "samples (marching cubes) or voxels (TSDF) along the box's longest side"
    )
    threshold: float = opt(
        0.0,
        "marching-cubes density level; 0 = ln 2 / voxel size (opacity 0.5 per voxel), or less for a field softer than that (soft_field_threshold)",
    )
    threshold_views: int = opt(
        6, "training views rendered to find the density at the rendered surface (threshold 0)"
    )
    truncation: float = opt(0.02, "TSDF truncation as a fraction of the box's longest side")
    min_component: float = opt(0.02, "components with fewer faces than this fraction are removed")
    visible_only: bool = opt(
        True,
        "marching cubes: keep only faces a training camera sees (within visible_tolerance of the "
        "front surface): drops the back sheet of a density shell and the sides of a level set "
        "no photo shows (sample_data sdf, 10 min: F 0.855 -> 0.905); off: the closed level set",
    )
    visible_tolerance: float = opt(
        2.0, "how far behind the front surface a face still counts as seen (voxels)"
    )
    format: str = opt("ply", "mesh file format", choices=("ply", "obj", "glb"))
    previews: int = opt(3, "shaded pictures of the mesh from this many training cameras")
    preview_max_side: int = opt(320, "longer side of the preview pictures (px)")
    device: str = opt(
        "auto", "auto (CUDA when available) | cpu | cuda", choices=("auto", "cpu", "cuda")
    )


def rendered_surface_density(
    model, scene, cfg: MeshConfig, device, downscale: int = 1
) -> np.ndarray:
    """Density (N,) at the expected depth of the pixels with opacity > 0.5 in a few training views."""
    from recon.cameras import camera_rays

    idx = scene.split("train")
    idx = idx[:: max(1, len(idx) // max(1, cfg.threshold_views))][: cfg.threshold_views]
    cams = scene.cameras(idx, device, downscale)
    values = []
    with torch.no_grad():
        for i in range(len(cams)):
            out = model.render(cams[i])
            origins, dirs, z_per_t = camera_rays(cams, i)
            hit = out["acc"] > 0.5
            points = (origins + dirs * (out["depth"] / z_per_t)[..., None])[hit]
            values.append(model.density(points.reshape(-1, 3)).reshape(-1).float().cpu().numpy())
    return np.concatenate(values) if values else np.zeros(0)


def field_normals(model, vertices: np.ndarray, device, chunk: int = 1 << 15) -> np.ndarray:
    """Unit normals (N, 3) at mesh vertices (N, 3) from the gradient of the signed distance
    field (not from the faces): exact for the surface the field holds."""
    out = []
    points = torch.as_tensor(np.asarray(vertices), dtype=torch.float32, device=device)
    for start in range(0, len(points), chunk):
        g = model.sdf_gradient(points[start : start + chunk]).detach()
        out.append(torch.nn.functional.normalize(g, dim=-1).cpu().double().numpy())
    return np.concatenate(out)


def mesh_run(ws: Workspace, run: str, cfg: MeshConfig, force: bool = False, progress=None) -> dict:
    key = f"train/{run}"
    ws.require_fresh(key, force)
    device = pick_device(cfg.device)
    model, scene, run_doc = load_run(ws, run, device)
    level = trained_resolution(run_doc, scene).downscale  # views are rendered at the training size
    aabb = scene.info.aabb.to(device)
    method = cfg.method
    has_sdf = model.has_sdf
    if method == "auto":
        method = "marching-cubes" if has_sdf else "tsdf"
    started = time.time()
    side = float((aabb[1] - aabb[0]).max())  # the box's longest side
    if method == "marching-cubes" and has_sdf:
        # the surface is the zero level set of the distance, inside where it is negative
        mesh = extract_density_mesh(
            lambda p: -model.sdf(p),
            aabb,
            cfg.resolution,
            0.0,
            color_fn=model.point_colors,
            device=device,
        )
        detail = {"level": "sdf = 0", "normals": "field gradient"}
    elif method == "marching-cubes":
        if not model.has_density:
            raise WorkspaceError(
                f"run '{run}' ({run_doc['method']}) has no density field: use --method tsdf"
            )
        threshold = cfg.threshold or soft_field_threshold(
            choose_density_threshold(side / cfg.resolution),
            rendered_surface_density(model, scene, cfg, device, level),
        )
        color_fn = model.point_colors if model.has_point_colors else None
        mesh = extract_density_mesh(
            model.density, aabb, cfg.resolution, threshold, color_fn=color_fn, device=device
        )
        detail = {"threshold": threshold}
    elif method == "tsdf":
        idx = scene.split("train")
        cams = scene.cameras(idx, device, level)
        depths, rgbs = [], []
        for i in range(len(cams)):
            with torch.no_grad():
                out = model.render(cams[i])
            # pixels the model leaves empty carve free space: give them a depth beyond the box
            far = torch.full_like(out["depth"], 1e3)
            depths.append(torch.where(out["acc"] > 0.5, out["depth"], far))
            rgbs.append(out["rgb"].clamp(0, 1))
            if progress:
                progress("render depth", i + 1, len(cams))
        tcfg = TSDFConfig(resolution=cfg.resolution, truncation=cfg.truncation)
        mesh = fuse_depth_maps(cams, torch.stack(depths), torch.stack(rgbs), aabb, tcfg)
        detail = {"views": len(cams)}
    else:
        raise WorkspaceError(f"unknown mesh method {cfg.method!r}")
    if len(mesh.faces) == 0:
        raise WorkspaceError(f"the {method} mesh of run '{run}' is empty: is the run trained?")
    raw_faces = len(mesh.faces)
    cams = scene.cameras(scene.split("train"), "cpu", level)
    mesh = keep_seen_components(
        mesh, cams.K.numpy(), cams.cam_from_world.numpy(),
        torch.stack([cams.width, cams.height], 1).numpy(),
    )  # fmt: skip
    if cfg.visible_only and method == "marching-cubes":
        mesh = keep_visible_faces(
            mesh,
            cams.K.numpy(),
            cams.cam_from_world.numpy(),
            torch.stack([cams.width, cams.height], 1).numpy(),
            cfg.visible_tolerance * side / cfg.resolution,
        )
        detail["visible_faces"] = len(mesh.faces)
    mesh = remove_small_components(mesh, cfg.min_component)
    normals = None
    if has_sdf and method == "marching-cubes" and len(mesh.vertices):
        normals = field_normals(model, mesh.vertices, device)
    previews = write_previews(
        ws.mesh_dir(run), mesh, scene, cfg.previews, cfg.preview_max_side, normals
    )
    sim = scene.scene_from_world
    mesh = mesh_to_original_units(mesh, sim)
    if normals is not None:  # directions turn with R^T: n_world = R^T n_scene
        mesh.vertex_normals = normals @ np.asarray(sim.R, np.float64)
    out_path = ws.mesh_dir(run) / f"mesh.{cfg.format}"
    write_mesh(mesh, out_path)
    stats = mesh_stats(mesh)
    result = {
        "run": run,
        "method": method,
        "path": str(out_path),
        "faces_before_cleanup": raw_faces,
        **{k: (v.item() if isinstance(v, np.generic) else v) for k, v in stats.items()},
        "seconds": round(time.time() - started, 2),
        "previews": previews,
        **detail,
    }
    atomic_write_json(ws.mesh_json(run), result)
    ws.record_stage(
        f"mesh/{run}",
        config=asdict(cfg),
        inputs={"model": ws.model_path(run)},
        outputs={"mesh": out_path},
        upstream=[key],
        started=started,
        ended=time.time(),
        extra={"faces": result.get("faces")},
    )
    return result


def write_previews(
    out_dir, mesh, scene, count: int, max_side: int, normals: np.ndarray | None = None
) -> list[str]:
    """Shaded pictures of `mesh` (in the scene frame, as the cameras) from `count` cameras, at
    most `max_side` px -> out_dir/preview_<k>.png; the names. The first
    is the first held-out camera (a view no training image fixed), the others spread over the
    training cameras. Per-vertex `normals` (the field's) shade smoothly, else the faces'."""
    held_out = scene.split("test")[:1]
    train = scene.split("train")
    picks = list(held_out) + [train[k] for k in preview_views(len(train), count - 1)]
    picks = picks[:count]
    if not picks:
        return []
    k = downscale_for_max_side(*scene.image_size("train"), max_side)
    cams = scene.cameras(picks, "cpu", k)
    colours = None
    if getattr(mesh.visual, "kind", None) == "vertex":
        colours = np.asarray(mesh.visual.vertex_colors)[:, :3] / 255.0
    names = []
    for j in range(len(picks)):
        image, _ = shade_mesh(
            np.asarray(mesh.vertices),
            np.asarray(mesh.faces),
            cams.K[j].numpy(),
            cams.cam_from_world[j].numpy(),
            int(cams.width[j]),
            int(cams.height[j]),
            colours,
            normals,
        )
        name = f"preview_{j}.png"
        write_png(out_dir / name, image)
        names.append(name)
    return names


def read_mesh_json(ws: Workspace, run: str) -> dict | None:
    p = ws.mesh_json(run)
    return json.loads(p.read_text()) if p.exists() else None
