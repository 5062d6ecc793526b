"""The `eval` stage: held-out renders -> PSNR / SSIM / LPIPS / depth error, mesh -> geometry
error against ground truth, sfm -> pose error against reference poses, log -> speed.
Writes runs/<run>/eval/metrics.json, then report.md and speed_vs_error.png for all runs."""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from recon.eval.html import write_html_report
from recon.eval.report import write_report
from recon.eval.sfm_plot import plot_sfm
from recon.eval.speed import read_log, speed_metrics
from recon.eval.viewer import write_viewer
from recon.eval.visuals import write_view_pictures
from recon.io.exr import read_depth_exr
from recon.metrics.image import border_mask, depth_errors, psnr, psnr_masked, ssim
from recon.models.registry import pick_device
from recon.options import opt
from recon.render.views import render_view
from recon.train.resolution import output_levels
from recon.workspace import Workspace, WorkspaceError, atomic_write_json
from recon.workspace.runs import load_run
from recon.workspace.scene import level_size
from recon.workspace.workspace import MVS_RESULT


@dataclass(frozen=True)
class EvalConfig:
    split: str = opt("test", "held-out split")
    every: int = opt(1, "evaluate every N-th view of the split (lego-200 protocol: 8)")
    gt_mesh: str = opt(
        "", "ground-truth mesh (original units); default: the dataset's, if it has one"
    )
    gt_points: str = opt("", "ground-truth point cloud (original units), instead of a mesh")
    tau: float = opt(
        0.0, "F-score threshold in original units (0 = 1 % of the GT bounding-box diagonal)"
    )
    gt_poses: str = opt(
        "", "reference poses (transforms.json or COLMAP model) for sfm pose accuracy"
    )
    lpips: bool = opt(True, "compute LPIPS when its weights are available")
    max_side: int = opt(
        0,
        "evaluate at the pyramid level whose longer side fits N px (0 = the run's training level)",
    )
    downscale: int = opt(
        0, "evaluate at the sfm images downscaled by K (0 = the run's training level)"
    )
    photo_size: bool = opt(
        True,
        "also score at the photos' own size (the sfm images) when the views are scored coarser: "
        "the direct render and, beside it, the coarser render upsampled (bicubic)",
    )
    border: float = opt(
        0.15, "PSNR is also reported on the outer band of this fraction of each side"
    )
    mvs: bool = opt(
        True,
        "without --run: also score the geometry of `recon mvs`'s mesh (WS/mvs/mesh.ply) when "
        "it exists (--run mvs scores it alone)",
    )
    pictures: bool = opt(
        True, "write photo / render / error / depth pictures of each view for report.html"
    )
    viewer: bool = opt(
        True, "write each run's interactive 3D view for report.html (viewer/<run>.js beside it)"
    )
    device: str = opt(
        "auto", "auto (CUDA when available) | cpu | cuda", choices=("auto", "cpu", "cuda")
    )


def _nanmean(values: list[float]) -> float:
    """The mean over the views where a metric is defined (not NaN); NaN if it is defined on none
    (without numpy's empty-slice warning)."""
    finite = [v for v in values if not math.isnan(v)]
    return float(np.mean(finite)) if finite else float("nan")


def image_metrics(ws: Workspace, run: str, cfg: EvalConfig, device, lpips_model) -> dict:
    from recon.metrics.lpips import lpips
    from recon.workspace.scene import load_images

    model, scene, run_doc = load_run(ws, run, device)
    idx = scene.split(cfg.split)[:: cfg.every]
    if not idx:
        raise WorkspaceError(f"the scene has no '{cfg.split}' views to evaluate")
    k_out, k_render = output_levels(scene, run_doc, cfg.max_side, cfg.downscale)
    cams = scene.cameras(idx, device, k_render)
    gts = load_images(ws, scene, idx, k_out).to(device)
    out_h, out_w = gts.shape[1:3]
    band = border_mask(out_h, out_w, cfg.border).to(device)
    per_view, times, pictures, preds = {}, [], {}, []
    for i, fi in enumerate(idx):
        t0 = time.perf_counter()
        out = render_view(model, cams[i], out_w, out_h)
        times.append(time.perf_counter() - t0)
        pred = out["rgb"].clamp(0, 1)
        preds.append(pred.cpu())
        m = {
            "psnr": float(psnr(pred, gts[i])),
            "ssim": float(ssim(pred, gts[i])),
            "psnr_border": float(psnr_masked(pred, gts[i], band)),
        }
        if lpips_model is not None:
            m["lpips"] = float(lpips(pred, gts[i], lpips_model))
        gt_depth_path = scene.frames[fi].get("depth_gt")
        if gt_depth_path and Path(gt_depth_path).exists():
            gt_d = read_depth_exr(gt_depth_path)
            h, w = pred.shape[:2]
            gt_d = cv2.resize(gt_d, (w, h), interpolation=cv2.INTER_NEAREST)
            pred_d = scene.depth_to_world_units(out["depth"].cpu().numpy())
            pred_d = np.where(out["acc"].cpu().numpy() > 0.5, pred_d, 0.0)
            errs = depth_errors(
                torch.from_numpy(pred_d),
                torch.from_numpy(gt_d),
                torch.from_numpy((pred_d > 0) & (gt_d > 0)),
            )
            m.update({f"depth_{k}": v for k, v in errs.items() if k != "count"})
        per_view[scene.frames[fi]["name"]] = m
        if cfg.pictures:
            pictures[scene.frames[fi]["name"]] = write_view_pictures(
                ws.eval_dir(run) / "views",
                scene.frames[fi]["name"],
                gts[i].cpu().numpy(),
                pred.cpu().numpy(),
                out["depth"].float().cpu().numpy(),
                out["acc"].float().cpu().numpy(),
            )
    keys = sorted({k for v in per_view.values() for k in v})
    mean = {k: _nanmean([v[k] for v in per_view.values() if k in v]) for k in keys}
    sfm_size = scene.image_size("train")
    finer = cfg.photo_size and k_out > 1
    return {
        **(
            {"photo_size": photo_size_metrics(ws, model, scene, idx, preds, device, lpips_model)}
            if finer
            else {}
        ),
        "per_view": per_view,
        "pictures": pictures,
        "mean": mean,
        "views": len(idx),
        "render_ms_per_frame": round(1000 * float(np.median(times)), 2),
        "resolution": [int(out_w), int(out_h)],
        "downscale": k_out,
        "rendered_at": {"downscale": k_render, "size": list(level_size(*sfm_size, k_render))},
        "border_fraction": cfg.border,
    }


def photo_size_metrics(ws: Workspace, model, scene, idx, low, device, lpips_model) -> dict:
    """The held-out views at the photos' own size (pyramid level 1): PSNR / SSIM (/ LPIPS) of
    the model rendered there ("direct") and of its renders at the evaluated size `low`
    ((H, W, 3) each; by default the training size) upsampled bicubically ("upsampled"). A
    model that renders finer than it trained no better than its upscaled image aliases there
    (the zoom-in artefact of Yu et al. 2024, "Mip-Splatting": the dilation and sub-pixel
    splats a training size never saw)."""
    from recon.metrics.lpips import lpips
    from recon.workspace.scene import load_images

    cams = scene.cameras(idx, device, 1)
    rows: dict[str, list[dict]] = {"direct": [], "upsampled": []}
    for i in range(len(idx)):
        gt = load_images(ws, scene, [idx[i]], 1)[0].to(device)
        h, w = gt.shape[:2]
        direct = render_view(model, cams[i], w, h)["rgb"].clamp(0, 1)
        up = cv2.resize(low[i].float().numpy(), (w, h), interpolation=cv2.INTER_CUBIC)
        up = torch.from_numpy(up).clamp(0, 1).to(device)
        for name, img in (("direct", direct), ("upsampled", up)):
            m = {"psnr": float(psnr(img, gt)), "ssim": float(ssim(img, gt))}
            if lpips_model is not None:
                m["lpips"] = float(lpips(img, gt, lpips_model))
            rows[name].append(m)
    w, h = scene.image_size("train")
    means = {n: {k: _nanmean([r[k] for r in rs]) for k in rs[0]} for n, rs in rows.items()}
    return {
        "resolution": [int(w), int(h)],
        "downscale": 1,
        "mean": means["direct"],
        "upsampled": means["upsampled"],
    }


def observed_fn(scene, tol: float):
    """GT points -> seen by some view, from the dataset's depth maps (None without them)."""
    from recon.metrics.geometry import observed_by_depth

    frames = scene.frames
    if not frames or not all(f.get("depth_gt") and Path(f["depth_gt"]).exists() for f in frames):
        return None
    sim = scene.scene_from_world
    scene_from_orig = np.eye(4)
    scene_from_orig[:3, :3], scene_from_orig[:3, 3] = sim.scale * sim.R, sim.t
    orig_from_scene_units = np.diag(
        [1 / sim.scale] * 3 + [1.0]
    )  # camera frame back to original units
    mats = np.stack(
        [orig_from_scene_units @ np.asarray(f["cam_from_world"]) @ scene_from_orig for f in frames]
    )
    Ks = np.array([[[f["fx"], 0, f["cx"]], [0, f["fy"], f["cy"]], [0, 0, 1.0]] for f in frames])
    depths = [
        cv2.resize(
            read_depth_exr(f["depth_gt"]),
            (f["width"], f["height"]),
            interpolation=cv2.INTER_NEAREST,
        )
        for f in frames
    ]
    return lambda points: observed_by_depth(points, mats, Ks, depths, tol)


def align_to_reference(mesh, poses: dict) -> str:
    """Move `mesh` (trimesh, our world frame) into the reference's frame with the Sim3 of the
    camera centres found by `pose_section` (x_ref = s A x + b); returns what was done. A mesh
    made from SfM poses lives in the SfM's own frame and scale: without this its distances to
    the ground truth would measure the frame, not the surface."""
    if poses.get("status") != "ok" or "sim3" not in poses:
        return "none"
    sim = poses["sim3"]
    A, b = np.asarray(sim["rotation"]), np.asarray(sim["translation"])
    mesh.vertices = sim["scale"] * np.asarray(mesh.vertices) @ A.T + b
    return f"Sim3 of the camera centres onto --gt-poses (scale {sim['scale']:.6g})"


def geometry_section(
    ws: Workspace,
    run: str,
    cfg: EvalConfig,
    scene_gt_mesh: str | None,
    scene=None,
    poses: dict | None = None,
) -> dict:
    gt_path = cfg.gt_points or cfg.gt_mesh or scene_gt_mesh
    if not gt_path:
        return {"status": "no ground truth (pass --gt-mesh or --gt-points)"}
    meshes = sorted(ws.mesh_dir(run).glob("mesh.*")) if ws.mesh_dir(run).exists() else []
    meshes = [m for m in meshes if m.suffix in (".ply", ".obj", ".glb")]
    if not meshes:
        return {
            "status": f"no mesh for run '{run}': run `recon mesh -w {ws.root} --run {run}` first",
            "gt": str(gt_path),
        }
    return mesh_geometry(meshes[0], gt_path, cfg, scene, poses)


def mesh_geometry(mesh_path, gt_path, cfg: EvalConfig, scene=None, poses=None) -> dict:
    """Geometry metrics of the mesh at mesh_path (original units) against the ground truth."""
    import trimesh

    from recon.metrics.geometry import geometry_metrics

    gt = trimesh.load(str(gt_path), process=False, force=None)
    pred = trimesh.load(str(mesh_path), process=False, force="mesh")
    aligned = align_to_reference(pred, poses or {})
    diag = float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))
    tau = cfg.tau or 0.01 * diag
    observed = observed_fn(scene, tau) if scene is not None and not cfg.gt_points else None
    if observed is None and aligned != "none" and not cfg.gt_points:
        from recon.eval.poses import reference_observed_fn

        observed = reference_observed_fn(Path(cfg.gt_poses), tau)
    m = geometry_metrics(pred, gt, tau, gt_observed_fn=observed)
    return {
        "status": "ok",
        "gt": str(gt_path),
        "mesh": str(mesh_path),
        "aligned": aligned,
        "tau": tau,
        **{k: float(v) for k, v in m.items() if np.isscalar(v)},
    }


def pose_section(ws: Workspace, cfg: EvalConfig) -> dict:
    if not cfg.gt_poses:
        return {"status": "no reference poses (pass --gt-poses)"}
    from recon.eval.poses import sfm_pose_accuracy

    return sfm_pose_accuracy(ws, Path(cfg.gt_poses))


def evaluate(
    ws: Workspace, runs: list[str], cfg: EvalConfig, force: bool = False, progress=None
) -> dict:
    from recon.metrics.lpips import NETWORK, load_lpips
    from recon.workspace.scene import load_scene

    asked_mvs = MVS_RESULT in runs  # `--run mvs`: the mesh of `recon mvs`
    if asked_mvs and not ws.mvs_mesh.exists():
        raise WorkspaceError(f"{ws.root} has no mvs mesh: run `recon mvs -w {ws.root}` first")
    # no --run: every trained run, and the mvs mesh when there is one (unless --no-mvs)
    with_mvs = asked_mvs or (not runs and cfg.mvs and ws.mvs_mesh.exists())
    runs = [r for r in runs if r != MVS_RESULT]
    if not runs and not asked_mvs:
        runs = [r for r in ws.runs() if ws.model_path(r).exists()]
    if not runs and cfg.gt_poses and not with_mvs:  # the sfm stage alone: pose accuracy
        poses = pose_section(ws, cfg)
        atomic_write_json(ws.pose_accuracy_json, poses)
        return {"sfm": {"pose": poses}}
    if not runs and not with_mvs:
        raise WorkspaceError(
            f"no trained run in {ws.root}: run `recon train` first "
            "(or pass --gt-poses to evaluate the sfm poses alone)"
        )
    scene = load_scene(ws, with_points=False)
    poses = pose_section(ws, cfg)
    results = {}
    if runs:
        device = pick_device(cfg.device)
        lpips_model = load_lpips(device) if cfg.lpips else None
        lpips_note = (
            NETWORK
            if lpips_model is not None
            else "LPIPS unavailable (weights could not be obtained)"
        )
    for k, run in enumerate(runs):
        ws.require_fresh(f"train/{run}", force)
        started = time.time()
        run_doc, log = _run_doc(ws, run), read_log(ws.log_jsonl(run))
        metrics = {
            "run": run,
            "method": run_doc["method"],
            "split": cfg.split,
            "lpips_network": lpips_note,
            **image_metrics(ws, run, cfg, device, lpips_model),
            "geometry": geometry_section(ws, run, cfg, scene.gt_mesh, scene, poses),
            "pose": poses,
            "speed": speed_metrics(run_doc, log),
        }
        metrics = _finite(metrics)
        atomic_write_json(ws.metrics_json(run), metrics)
        ws.record_stage(
            f"eval/{run}",
            config=asdict(cfg),
            inputs={"model": ws.model_path(run)},
            outputs={"metrics": ws.metrics_json(run)},
            upstream=[f"train/{run}"],
            started=started,
            ended=time.time(),
        )
        results[run] = metrics
        if cfg.viewer:
            write_viewer(ws, run)
        if progress:
            progress("eval", k + 1, len(runs), run=run, psnr=round(metrics["mean"]["psnr"], 2))
    if with_mvs:
        results[MVS_RESULT] = mvs_metrics(ws, cfg, scene, poses)
    # concurrent evaluations of one workspace (a sweep's jobs) write the report one at a time,
    # each from every metrics.json on disk, so the last one written lists them all
    with ws.writer_lock("report", wait=True):
        all_metrics = {r: _load_metrics(ws, r) for r in ws.runs()}
        done = {r: m for r, m in all_metrics.items() if m is not None}
        if ws.mvs_metrics_json.exists():  # (a new `recon mvs` replaces WS/mvs/ and drops it)
            done[MVS_RESULT] = json.loads(ws.mvs_metrics_json.read_text())
        write_report(ws, done)
        plot_sfm(ws, load_scene(ws))
        write_html_report(ws, done)
    return results


def mvs_metrics(ws: Workspace, cfg: EvalConfig, scene, poses: dict) -> dict:
    """The geometry of `recon mvs`'s mesh -> WS/mvs/metrics.json (it has no images to score)."""
    gt_path = cfg.gt_points or cfg.gt_mesh or scene.gt_mesh
    geometry = (
        mesh_geometry(ws.mvs_mesh, gt_path, cfg, scene, poses)
        if gt_path
        else {"status": "no ground truth (pass --gt-mesh or --gt-points)"}
    )
    stage = json.loads(ws.mvs_json.read_text()) if ws.mvs_json.exists() else {}
    speed = {"train_wall_s": stage.get("seconds"), "trained_at": stage.get("size")}
    metrics = _finite({"run": MVS_RESULT, "method": "mvs", "geometry": geometry, "speed": speed})
    atomic_write_json(ws.mvs_metrics_json, metrics)
    return metrics


def _run_doc(ws: Workspace, run: str) -> dict:
    return json.loads(ws.run_json(run).read_text())


def _load_metrics(ws: Workspace, run: str) -> dict | None:
    p = ws.metrics_json(run)
    return json.loads(p.read_text()) if p.exists() else None


def _finite(obj):
    """JSON has no inf/nan: write them as strings ("inf") so readers see them plainly."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    return obj
