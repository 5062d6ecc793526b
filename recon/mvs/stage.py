"""The `mvs` stage: the sfm cameras and training photos -> dense depth maps, a fused point
cloud and its mesh in WS/mvs/ (original scene units), by classical multi-view stereo.

Per training view: plane-sweep stereo against its `sources` nearest training views (by
viewing direction; `plane_sweep`), then the multi-view geometric check (`consistency`): a
depth survives when `min_views` other views' depth maps agree with it. The survivors are
fused into points (each the mean of the agreeing views' points) and, by TSDF fusion of the
filtered depth maps, into a mesh. Held-out views are never read. Only the scene box is
reconstructed: the planes span the box's depth range and points outside it are dropped.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np
import torch
import trimesh

from recon.cameras import Cameras
from recon.cameras.rays import project_points
from recon.io.atomic import atomic_dir
from recon.io.exr import write_depth_exr
from recon.io.ply import write_points_ply
from recon.mesh.cleanup import (
    keep_seen_components,
    mesh_stats,
    mesh_to_original_units,
    remove_small_components,
    write_mesh,
)
from recon.mesh.stage import write_previews
from recon.mesh.tsdf import TSDFConfig, fuse_depth_maps
from recon.models.registry import pick_device
from recon.mvs.consistency import consistent_views
from recon.mvs.plane_sweep import best_depth, inverse_depth_planes, sweep_scores
from recon.options import opt
from recon.train.resolution import downscale_for_max_side
from recon.workspace import Workspace, WorkspaceError, atomic_write_json
from recon.workspace.scene import load_images, load_scene


@dataclass(frozen=True)
class MvsConfig:
    max_side: int = opt(
        640, "longer side (px) of the images the depth maps are computed at (a pyramid level)"
    )
    planes: int = opt(192, "depth hypotheses over the box's depth range, uniform in 1/depth")
    window: int = opt(7, "side (px, odd) of the patches compared by normalized cross-correlation")
    sources: int = opt(4, "training views compared with each view: the nearest by direction")
    top_k: int = opt(2, "the best-scoring sources averaged per depth (robust to occlusion)")
    min_score: float = opt(0.3, "a depth whose mean NCC is below this is dropped")
    min_views: int = opt(
        1,
        "other views whose depth maps must agree with a depth for it to enter the mesh (TSDF "
        "fusion averages what is left, and removing small components drops the rest)",
    )
    point_views: int = opt(
        2, "other views that must agree with a depth for its point to enter points.ply"
    )
    max_reprojection: float = opt(1.0, "agreement: reprojection error below this (px)")
    max_depth_ratio: float = opt(0.01, "agreement: depth difference below this fraction")
    resolution: int = opt(256, "TSDF voxels along the box's longest side (the mesh)")
    truncation: float = opt(0.01, "TSDF truncation as a fraction of the box's longest side")
    min_component: float = opt(
        0.02, "mesh components with fewer faces than this fraction are removed"
    )
    previews: int = opt(3, "shaded pictures of the mesh from this many cameras")
    device: str = opt(
        "auto", "auto (CUDA when available) | cpu | cuda", choices=("auto", "cpu", "cuda")
    )


def source_views(cameras: Cameras, reference: int, count: int) -> list[int]:
    """The `count` other cameras whose optical axes are closest in angle to the reference's."""
    axes = cameras.cam_from_world[:, 2, :3]  # row 3 of R: the optical axis in the world
    cosine = axes @ axes[reference]
    cosine[reference] = -2.0
    return torch.argsort(cosine, descending=True)[:count].tolist()


def box_depth_range(aabb: torch.Tensor, cam_from_world: torch.Tensor) -> tuple[float, float]:
    """Nearest and farthest z-depth of the box's 8 corners in a camera (near >= 1e-3 far)."""
    corners = torch.cartesian_prod(aabb[:, 0], aabb[:, 1], aabb[:, 2])
    z = (corners @ cam_from_world[:3, :3].T + cam_from_world[:3, 3])[:, 2]
    far = float(z.max())
    if far <= 0:
        raise WorkspaceError("the scene box is behind a training camera")
    return max(float(z.min()), 1e-3 * far), far


MIN_RANGE_POINTS = 20  # sparse points a view must see for them to set its depth range


def view_depth_range(
    aabb: torch.Tensor, cam_from_world: torch.Tensor, K: torch.Tensor, size, points=None
) -> tuple[float, float]:
    """The depth range swept for one view: the 1st-99th percentile of the z-depths of the sfm
    points it sees, widened by 20 % each way and kept inside the box's range (as COLMAP's
    patch-match stereo takes each image's range from the sparse points); the box's range
    (`box_depth_range`) when the scene has fewer such points (imported poses). A camera inside
    the box (a capture normalized as unbounded) would otherwise sweep from 1e-3 of the box's
    far side and spend most planes where nothing is."""
    near, far = box_depth_range(aabb, cam_from_world)
    if points is None or len(points) < MIN_RANGE_POINTS:
        return near, far
    uv, z = project_points(points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3], K)
    seen = (z > 0) & (uv >= 0).all(-1) & (uv[:, 0] < size[0]) & (uv[:, 1] < size[1])
    if int(seen.sum()) < MIN_RANGE_POINTS:
        return near, far
    lo, hi = torch.quantile(z[seen].float(), torch.tensor([0.01, 0.99], device=z.device))
    return max(near, float(lo) / 1.2), min(far, float(hi) * 1.2)


def view_depths(grey, cameras: Cameras, aabb, cfg: MvsConfig, points=None, progress=None):
    """Plane-sweep depth (C, H, W) and score (C, H, W) of every view (grey (C, H, W)); each
    view's planes span `view_depth_range` (points: the sfm points (P, 3) or None)."""
    depths, scores = [], []
    size = (grey.shape[2], grey.shape[1])
    for r in range(len(cameras)):
        src = source_views(cameras, r, cfg.sources)
        near, far = view_depth_range(aabb, cameras.cam_from_world[r], cameras.K[r], size, points)
        planes = inverse_depth_planes(near, far, cfg.planes).to(grey.device)
        volume = sweep_scores(
            grey[r],
            [grey[s] for s in src],
            cameras.K[r],
            [cameras.K[s] for s in src],
            [cameras.cam_from_world[s] @ cameras.world_from_cam[r] for s in src],
            planes,
            cfg.window,
            cfg.top_k,
        )
        depth, score = best_depth(volume, planes)
        depths.append(depth)
        scores.append(score)
        if progress:
            progress("depth maps", r + 1, len(cameras))
    return torch.stack(depths), torch.stack(scores)


def filter_depths(depths, scores, cameras: Cameras, aabb, cfg: MvsConfig):
    """Keep the depths that score >= min_score, that min_views other views agree with and whose
    point lies in the box. Returns the filtered depths (C, H, W; 0 = dropped) and, per view,
    the fused points (N_c, 3) of the depths that point_views other views agree with and the
    (H, W) masks of their pixels (for their colours)."""
    scored = torch.where(scores >= cfg.min_score, depths, 0.0)
    kept, points, colour_masks = [], [], []
    for r in range(len(cameras)):
        count, fused = consistent_views(
            scored, cameras, r, cfg.max_reprojection, cfg.max_depth_ratio
        )
        inside = ((fused >= aabb[0]) & (fused <= aabb[1])).all(-1)
        keep = (scored[r] > 0) & inside
        kept.append(torch.where(keep & (count >= cfg.min_views), depths[r], 0.0))
        confirmed = keep & (count >= cfg.point_views)
        points.append(fused[confirmed])
        colour_masks.append(confirmed)
    return torch.stack(kept), points, colour_masks


def run_mvs(ws: Workspace, cfg: MvsConfig, force: bool = False, progress=None) -> dict:
    if cfg.window < 3 or cfg.window % 2 == 0:
        raise WorkspaceError(f"--window must be an odd number >= 3, got {cfg.window}")
    if cfg.planes < 3:
        raise WorkspaceError(f"--planes must be at least 3, got {cfg.planes}")
    ws.require_fresh("sfm", force)
    started = time.time()
    device = pick_device(cfg.device)
    scene = load_scene(ws)
    idx = scene.split("train")
    if len(idx) < 2:
        raise WorkspaceError(f"mvs needs at least 2 training views, the scene has {len(idx)}")
    level = downscale_for_max_side(*scene.image_size("train"), cfg.max_side)
    with ws.writer_lock("mvs"):
        rgb = load_images(ws, scene, idx, level).to(device)
        cams = scene.cameras(idx, device, level)
        aabb = scene.info.aabb.to(device=device, dtype=torch.float32)
        with torch.no_grad():
            sparse = scene.info.points  # the sfm points set each view's depth range
            sparse = None if sparse is None else sparse.to(device)
            depths, scores = view_depths(rgb.mean(-1), cams, aabb, cfg, sparse, progress)
            kept, points, masks = filter_depths(depths, scores, cams, aabb, cfg)
            tcfg = TSDFConfig(resolution=cfg.resolution, truncation=cfg.truncation)
            mesh = fuse_depth_maps(cams, kept, rgb, aabb.cpu().numpy(), tcfg)
        colours = torch.cat([rgb[c][m] for c, m in enumerate(masks)]).cpu()
        result = _write(ws, scene, idx, cams.to("cpu"), kept.cpu(), points, colours, mesh, cfg)
    result.update(
        {
            "views": len(idx),
            "size": [int(cams.width[0]), int(cams.height[0])],
            "downscale": level,
            "median_score": round(float(scores.median()), 4),
            "kept_fraction": round(float((kept > 0).float().mean()), 4),
            "seconds": round(time.time() - started, 2),
            "config": asdict(cfg),
        }
    )
    atomic_write_json(ws.mvs_json, result)
    ws.record_stage(
        "mvs",
        config=asdict(cfg),
        inputs={"cameras": ws.cameras_json},
        outputs={"mvs": ws.mvs_dir / ws.MVS_POINTS},
        upstream=["sfm"],
        started=started,
        ended=time.time(),
        extra={"points": result["points"], "faces": result["faces"]},
    )
    return result


def _write(ws, scene, idx, cams, kept, points, colours, mesh, cfg: MvsConfig) -> dict:
    """Depth maps (EXR, original units, 0 where dropped), points and mesh (original units) and
    previews -> WS/mvs/, built aside and swapped in whole."""
    sim = scene.scene_from_world
    if len(mesh.faces):
        mesh = keep_seen_components(
            mesh, cams.K.numpy(), cams.cam_from_world.numpy(),
            torch.stack([cams.width, cams.height], 1).numpy(),
        )  # fmt: skip
        mesh = remove_small_components(mesh, cfg.min_component)
    all_points = torch.cat(points).double().numpy()
    if len(all_points) == 0:
        raise WorkspaceError("mvs kept no depth: are the photos textured, the poses right?")
    with atomic_dir(ws.mvs_dir) as tmp:
        for c, i in enumerate(idx):
            name = scene.frames[i]["name"]
            depth = np.where(kept[c] > 0, scene.depth_to_world_units(kept[c].numpy()), 0.0)
            write_depth_exr(tmp / ws.MVS_DEPTH / f"{name}.exr", depth.astype(np.float32))
        write_points_ply(tmp / ws.MVS_POINTS, sim.invert_points(all_points), colours.numpy())
        # shaded by geometry alone: a dark object's vertex colours would hide its shape
        plain = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        previews = write_previews(tmp, plain, scene, cfg.previews, 320) if len(mesh.faces) else []
        stats = {"faces": 0}
        if len(mesh.faces):
            world = mesh_to_original_units(mesh, sim)
            write_mesh(world, tmp / ws.mvs_mesh.name)
            stats = mesh_stats(world)
    return {
        "points": len(all_points),
        "points_path": str(ws.mvs_dir / ws.MVS_POINTS),
        "mesh_path": str(ws.mvs_mesh) if stats["faces"] else None,
        **{k: (v.item() if isinstance(v, np.generic) else v) for k, v in stats.items()},
        "previews": previews,
    }
