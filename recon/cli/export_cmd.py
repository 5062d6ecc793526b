"""`recon export`: a 3dgs run as the de-facto INRIA splat PLY, in the original scene units."""

from __future__ import annotations

import time
from pathlib import Path

import click

from recon.cli.common import emit_json, json_option, workspace_option
from recon.workspace import Workspace, WorkspaceError, atomic_path


@click.command("export")
@workspace_option
@click.option("--run", required=True, help="A 3dgs run.")
@click.option("--format", "fmt", default="ply", type=click.Choice(["ply"]), show_default=True,
              help="ply: the INRIA splat PLY (x y z nx ny nz f_dc_* f_rest_* opacity scale_* rot_*).")
@click.option("--frame", default="world", type=click.Choice(["world", "scene"]), show_default=True,
              help="world: original units and axes (SH rotated exactly); scene: the normalized training frame.")
@click.option("-o", "--output", type=click.Path(path_type=Path), help="Output path (default WS/runs/RUN/export/splat.ply).")
@json_option
def command(workspace, run, fmt, frame, output, as_json):
    """Export a Gaussian-splat run -> WS/runs/RUN/export/splat.ply (loadable by common splat viewers)."""
    import numpy as np

    from recon.export.splat import gaussians_to_world
    from recon.gaussians.ply import write_splat_ply
    from recon.train.stage import load_model

    ws = Workspace.open(workspace)
    model, scene, run_doc = load_model(ws, run)
    if run_doc["method"] != "3dgs":
        raise WorkspaceError(f"run '{run}' is a {run_doc['method']} run; `recon export` writes Gaussian splats (3dgs)")
    p = {k: v.detach().cpu().numpy() for k, v in model.params.items()}
    g = {"means": p["means"], "quats": p["quats"], "log_scales": p["log_scales"],
         "opacity_logits": p["opacity_logits"].reshape(-1),
         "sh": np.concatenate([p["sh_dc"], p["sh_rest"]], axis=1)}
    if frame == "world":
        sim = scene.scene_from_world
        g = gaussians_to_world(g, sim.scale, sim.R, sim.t)
    out = output or ws.export_dir(run) / "splat.ply"
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    with atomic_path(out) as tmp:
        write_splat_ply(tmp, g["means"], g["quats"], g["log_scales"], g["opacity_logits"], g["sh"])
    result = {"run": run, "path": str(out), "gaussians": len(g["means"]), "frame": frame,
              "bytes": out.stat().st_size, "seconds": round(time.time() - t0, 3)}
    if as_json:
        emit_json(result)
    else:
        click.echo(f"export: {result['gaussians']} Gaussians ({frame} frame) -> {out}")
