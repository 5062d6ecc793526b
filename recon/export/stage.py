"""The `export` stage: a trained run in a format other tools read. Today: the Gaussians of a run
whose model `exports_splats`, as the INRIA splat PLY, in the world or the scene frame."""

from __future__ import annotations

import time
from pathlib import Path

from recon.gaussians.ply import write_splat_ply
from recon.gaussians.transform import gaussians_to_world
from recon.io.atomic import atomic_path
from recon.workspace import Workspace, WorkspaceError
from recon.workspace.runs import load_run

FRAMES = ("world", "scene")


def export_splats(
    ws: Workspace, run: str, frame: str = "world", output: Path | None = None
) -> dict:
    """Write the run's Gaussians -> output (default WS/runs/RUN/export/splat.ply); world: the
    capture's own units and axes (SH rotated exactly), scene: the normalized training frame."""
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {', '.join(FRAMES)}, got {frame!r}")
    model, scene, run_doc = load_run(ws, run)
    if not model.exports_splats:
        raise WorkspaceError(
            f"run '{run}' is a {run_doc['method']} run, which has no Gaussians to "
            "export (`recon export` writes the Gaussian splats of a 3dgs run)"
        )
    g = model.splats()
    if frame == "world":
        sim = scene.scene_from_world
        g = gaussians_to_world(g, sim.scale, sim.R, sim.t)
    out = output or ws.splat_ply(run)
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    with atomic_path(out) as tmp:
        write_splat_ply(tmp, g["means"], g["quats"], g["log_scales"], g["opacity_logits"], g["sh"])
    return {
        "run": run,
        "path": str(out),
        "gaussians": len(g["means"]),
        "frame": frame,
        "bytes": out.stat().st_size,
        "seconds": round(time.time() - t0, 3),
    }
