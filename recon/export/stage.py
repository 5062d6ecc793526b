"""The `export` stage: the Gaussians of a run whose model `exports_splats`, in the world or the
scene frame, in a format splat viewers open: the INRIA splat PLY (62 floats a Gaussian), the
32-byte `.splat`, or PlayCanvas's compressed PLY (16 bytes a Gaussian plus 3 per SH
coefficient kept); `sh_degree` drops the higher SH bands. An antialiased run's opacities are
written with their compensation averaged over the training views, since viewers do not
compensate."""

from __future__ import annotations

import time
from pathlib import Path

from recon.gaussians.ply import write_splat_ply
from recon.gaussians.splat_formats import write_compressed_ply, write_dot_splat
from recon.gaussians.transform import gaussians_to_world
from recon.io.atomic import atomic_path
from recon.train.resolution import trained_resolution
from recon.workspace import Workspace, WorkspaceError
from recon.workspace.runs import load_run

FRAMES = ("world", "scene")
# format -> default file name under WS/runs/RUN/export/ (SuperSplat recognises the
# compressed layout by its ".compressed.ply" ending)
FORMATS = {"ply": "splat.ply", "splat": "scene.splat", "compressed-ply": "scene.compressed.ply"}


def _write(fmt: str, path: Path, g: dict) -> None:
    args = (path, g["means"], g["quats"], g["log_scales"], g["opacity_logits"])
    if fmt == "ply":
        write_splat_ply(*args, g["sh"])
    elif fmt == "splat":
        write_dot_splat(*args, g["sh"][:, 0])
    else:
        write_compressed_ply(*args, g["sh"])


def export_splats(
    ws: Workspace,
    run: str,
    frame: str = "world",
    output: Path | None = None,
    fmt: str = "ply",
    sh_degree: int | None = None,
) -> dict:
    """Write the run's Gaussians -> output (default WS/runs/RUN/export/`FORMATS[fmt]`); world:
    the capture's own units and axes (SH rotated exactly), scene: the normalized training
    frame. sh_degree (0-3, default the model's) keeps the SH bands up to it."""
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {', '.join(FRAMES)}, got {frame!r}")
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if sh_degree is not None and not 0 <= sh_degree <= 3:
        raise ValueError(f"--sh-degree must be 0 to 3, got {sh_degree}")
    model, scene, run_doc = load_run(ws, run)
    if not model.exports_splats:
        raise WorkspaceError(
            f"run '{run}' is a {run_doc['method']} run, which has no Gaussians to "
            "export (`recon export` writes the Gaussian splats of a 3dgs run)"
        )
    # the training views at the resolution the run trained at: a model whose render-time terms
    # depend on the view (3dgs's antialiasing compensation) bakes their mean over them
    level = trained_resolution(run_doc, scene).downscale
    g = model.splats(scene.cameras(scene.split("train"), "cpu", level))
    if frame == "world":
        sim = scene.scene_from_world
        g = gaussians_to_world(g, sim.scale, sim.R, sim.t)
    model_degree = round(g["sh"].shape[1] ** 0.5) - 1
    degree = model_degree if sh_degree is None else min(sh_degree, model_degree)
    g = {**g, "sh": g["sh"][:, : (degree + 1) ** 2]}
    out = Path(output) if output else ws.export_dir(run) / FORMATS[fmt]
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    with atomic_path(out) as tmp:
        _write(fmt, tmp, g)
    return {
        "run": run,
        "path": str(out),
        "format": fmt,
        "gaussians": len(g["means"]),
        "sh_degree": 0 if fmt == "splat" else degree,
        "frame": frame,
        "antialias_baked": model.bakes_view_terms,
        "bytes": out.stat().st_size,
        "seconds": round(time.time() - t0, 3),
    }
