"""The `render` stage: dataset views or a camera path -> rgb/*.png, depth/*.exr (metric z-depth
in the ORIGINAL scene units), optional video.mp4, and the render time per frame."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass

import numpy as np
import torch

from recon.cameras.cameras import Cameras
from recon.io.exr import write_depth_exr
from recon.io.images import to_uint8, write_png
from recon.models.registry import pick_device
from recon.options import opt
from recon.render.paths import interpolate_path, orbit_path, spiral_path
from recon.render.views import render_view
from recon.train.resolution import output_levels
from recon.workspace import Workspace, WorkspaceError, atomic_path, atomic_write_json
from recon.workspace.runs import load_run
from recon.workspace.scene import level_size


@dataclass(frozen=True)
class RenderConfig:
    split: str = opt(
        "test", "dataset views to render (ignored with --path)", choices=("test", "train", "val")
    )
    path: str = opt(
        "", "a camera path instead of a split", choices=("", "orbit", "spiral", "interpolate")
    )
    frames: int = opt(60, "frames of the camera path")
    video: bool = opt(False, "also write video.mp4")
    fps: int = opt(30, "video frame rate")
    max_side: int = opt(
        0, "render at the pyramid level whose longer side fits N px (0 = the run's training level)"
    )
    downscale: int = opt(
        0, "render at the sfm images' size divided by K (0 = the run's training level)"
    )
    scale: float = opt(
        1.0,
        "output size x this, rendered at that size (4: a 200 px run at 800 px; 0.5: half)",
    )
    every: int = opt(1, "render every N-th view of the split (ignored with --path)")
    device: str = opt(
        "auto", "auto (CUDA when available) | cpu | cuda", choices=("auto", "cpu", "cuda")
    )


def path_cameras(
    scene, kind: str, frames: int, device, downscale: int = 1
) -> tuple[Cameras, list[str]]:
    """A camera path through the training views, with the first one's intrinsics at pyramid level
    `downscale`. The paths take and give `world_from_cam` poses; cameras keep `cam_from_world`."""
    train = scene.split("train")
    cams = scene.cameras(train, downscale=downscale).to(dtype=torch.float64)
    target = scene.info.aabb.double().mean(0)
    world_from_cam = cams.world_from_cam
    if kind == "orbit":
        cam_from_world = orbit_path(world_from_cam[:, :3, 3], target, frames)
    elif kind == "spiral":
        cam_from_world = spiral_path(world_from_cam, target, frames)
    elif kind == "interpolate":
        order = sorted(range(len(train)), key=lambda i: scene.frames[train[i]]["name"])
        cam_from_world = interpolate_path(world_from_cam[order], frames)
    else:
        raise WorkspaceError(f"unknown camera path {kind!r} (orbit, spiral, interpolate)")
    K = cams.K[:1].expand(frames, 3, 3).clone()
    out = Cameras(
        K,
        cam_from_world,
        cams.width[:1].expand(frames).clone(),
        cams.height[:1].expand(frames).clone(),
    )
    return out.to(device=device, dtype=torch.float32), [f"{i:04d}" for i in range(frames)]


def render_run(
    ws: Workspace, run: str, cfg: RenderConfig, force: bool = False, progress=None
) -> dict:
    key = f"train/{run}"
    ws.require_fresh(key, force)
    device = pick_device(cfg.device)
    model, scene, run_doc = load_run(ws, run, device)
    k_out, k_render = output_levels(scene, run_doc, cfg.max_side, cfg.downscale)
    if cfg.path:
        cams, names = path_cameras(scene, cfg.path, cfg.frames, device, k_render)
        sizes = [level_size(*scene.image_size("train"), k_out)] * len(cams)
        target = cfg.path
    else:
        split = scene.split(cfg.split)
        idx = split[:: cfg.every]
        if not idx:
            raise WorkspaceError(f"the scene has no '{cfg.split}' views")
        cams, names = scene.cameras(idx, device, k_render), [scene.frames[i]["name"] for i in idx]
        if cfg.split == "train":  # the training poses as the model refined them
            cams = model.train_cameras(cams, list(range(len(split)))[:: cfg.every])
        sizes = [
            level_size(scene.frames[i]["width"], scene.frames[i]["height"], k_out) for i in idx
        ]
        target = cfg.split
    if cfg.scale <= 0:
        raise ValueError(f"--scale must be > 0, got {cfg.scale}")
    if cfg.scale != 1:  # rendered straight at the new size: intrinsics scaled exactly
        sizes = [(max(1, round(w * cfg.scale)), max(1, round(h * cfg.scale))) for w, h in sizes]
        cams = cams.resized(
            torch.tensor([w for w, _ in sizes], device=cams.width.device),
            torch.tensor([h for _, h in sizes], device=cams.height.device),
        )
        target = f"{target}-x{cfg.scale:g}"  # beside the training-size renders, not over them
    out_dir = ws.renders_dir(run, target)
    started = time.time()
    times, frames_rgb = [], []
    for i in range(len(cams)):
        t0 = time.perf_counter()
        out = render_view(model, cams[i], *sizes[i])
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
        rgb = out["rgb"].clamp(0, 1).cpu().numpy()
        depth = out["depth"].float().cpu().numpy()
        acc = out["acc"].float().cpu().numpy()
        # pixels the scene does not cover have no surface: depth 0 (see recon.io.exr)
        depth_world = np.where(acc > 0.5, scene.depth_to_world_units(depth), 0.0).astype(np.float32)
        write_png(out_dir / "rgb" / f"{names[i]}.png", rgb)
        write_depth_exr(out_dir / "depth" / f"{names[i]}.exr", depth_world)
        if cfg.video:
            frames_rgb.append(to_uint8(rgb))
        if progress:
            progress("render", i + 1, len(cams), ms_per_frame=round(1000 * np.mean(times), 1))
    if cfg.video:
        write_video(ws.render_video(run, target), frames_rgb, cfg.fps)
    result = {
        "run": run,
        "target": target,
        "frames": len(cams),
        "out": str(out_dir),
        "ms_per_frame": round(1000 * float(np.mean(times)), 2),
        "ms_per_frame_median": round(1000 * float(np.median(times)), 2),
        "ms_first_frame": round(1000 * times[0], 2),
        "resolution": list(sizes[0]),
        "downscale": k_out,
        "rendered_at": {"downscale": k_render, "size": [int(cams.width[0]), int(cams.height[0])]},
        "device": str(device),
    }
    atomic_write_json(ws.render_json(run, target), result)
    ws.record_stage(
        f"render/{run}/{target}",
        config=cfg.__dict__,
        inputs={"model": ws.model_path(run)},
        outputs={"renders": out_dir},
        upstream=[key],
        started=started,
        ended=time.time(),
        extra={"ms_per_frame": result["ms_per_frame"]},
    )
    return result


def write_video(path, frames: list[np.ndarray], fps: int) -> None:
    import imageio.v2 as imageio

    with atomic_path(path) as tmp:
        # H.264 needs even sizes; pad by one pixel row/column if necessary
        h, w = frames[0].shape[:2]
        pad = ((0, h % 2), (0, w % 2), (0, 0))
        with imageio.get_writer(
            str(tmp), fps=fps, codec="libx264", quality=8, macro_block_size=1, format="FFMPEG"
        ) as writer:
            for f in frames:
                writer.append_data(np.pad(f, pad, mode="edge"))


def read_render_json(ws: Workspace, run: str, target: str) -> dict | None:
    p = ws.render_json(run, target)
    return json.loads(p.read_text()) if p.exists() else None
