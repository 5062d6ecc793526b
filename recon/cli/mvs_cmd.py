"""`recon mvs`: dense depth maps, fused points and a mesh from the sfm cameras (classical
multi-view stereo; no training)."""

from __future__ import annotations

import click

from recon.cli.common import emit_json, json_option, workspace_option
from recon.cli.progress import Progress
from recon.mvs.stage import MvsConfig, run_mvs
from recon.options import config_option, from_options
from recon.workspace import Workspace


@click.command("mvs")
@workspace_option
@config_option(MvsConfig, "max_side", type=click.IntRange(16))
@config_option(MvsConfig, "planes", type=click.IntRange(3))
@config_option(MvsConfig, "window", type=click.IntRange(3))
@config_option(MvsConfig, "sources", type=click.IntRange(1))
@config_option(MvsConfig, "top_k", type=click.IntRange(1))
@config_option(MvsConfig, "min_score", type=click.FloatRange(-1, 1))
@config_option(MvsConfig, "min_views", type=click.IntRange(0))
@config_option(MvsConfig, "point_views", type=click.IntRange(0))
@config_option(MvsConfig, "max_reprojection", type=click.FloatRange(0, min_open=True))
@config_option(MvsConfig, "max_depth_ratio", type=click.FloatRange(0, min_open=True))
@config_option(MvsConfig, "resolution", type=click.IntRange(16))
@config_option(MvsConfig, "truncation", type=click.FloatRange(0, min_open=True))
@config_option(MvsConfig, "min_component", type=click.FloatRange(0, 1))
@config_option(MvsConfig, "previews", type=click.IntRange(0))
@config_option(MvsConfig, "device")
@click.option("--force", is_flag=True, help="Run even if the sfm stage is stale.")
@json_option
def command(workspace, force, as_json, **options):
    """Plane-sweep stereo on the training photos, checked across views -> WS/mvs/:
    depth/<frame>.exr (channel Z, original units, 0 = no depth), points.ply and mesh.ply
    (original units), preview_*.png, mvs.json."""
    ws = Workspace.open(workspace)
    cfg = from_options(MvsConfig, options)
    with Progress(enabled=not as_json) as progress:
        result = run_mvs(ws, cfg, force, progress)
    if as_json:
        emit_json(result)
    else:
        w, h = result["size"]
        click.echo(
            f"mvs: {result['views']} views at {w}x{h}, {result['kept_fraction']:.0%} of the "
            f"pixels kept -> {result['points']} points, {result['faces']} faces in "
            f"{result['seconds']:.1f} s -> {result['points_path']}"
        )
