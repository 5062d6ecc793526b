"""`recon export`: a 3dgs run as the de-facto INRIA splat PLY, in the original scene units."""

from __future__ import annotations

from pathlib import Path

import click

from recon.cli.common import emit_json, json_option, workspace_option
from recon.workspace import Workspace


@click.command("export")
@workspace_option
@click.option("--run", required=True, help="A run whose model has Gaussians (3dgs).")
@click.option(
    "--format",
    "fmt",
    default="ply",
    type=click.Choice(["ply"]),
    show_default=True,
    help="ply: the INRIA splat PLY (x y z nx ny nz f_dc_* f_rest_* opacity scale_* rot_*).",
)
@click.option(
    "--frame",
    default="world",
    type=click.Choice(["world", "scene"]),
    show_default=True,
    help="world: original units and axes (SH rotated exactly); scene: the normalized training frame.",
)
@click.option(
    "-o",
    "--output",
    type=click.Path(path_type=Path),
    help="Output path (default WS/runs/RUN/export/splat.ply).",
)
@json_option
def command(workspace, run, fmt, frame, output, as_json):
    """Export a Gaussian-splat run -> WS/runs/RUN/export/splat.ply (loadable by common splat viewers)."""
    from recon.export.stage import export_splats

    result = export_splats(Workspace.open(workspace), run, frame, output)
    if as_json:
        emit_json(result)
    else:
        click.echo(f"export: {result['gaussians']} Gaussians ({frame} frame) -> {result['path']}")
