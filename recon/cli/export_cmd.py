"""`recon export`: a 3dgs run as a splat file viewers open (INRIA PLY, .splat, compressed PLY)."""

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
    type=click.Choice(["ply", "splat", "compressed-ply"]),
    show_default=True,
    help="ply: the INRIA splat PLY (62 floats a Gaussian); splat: the 32-byte .splat of web "
    "viewers (base colour only); compressed-ply: PlayCanvas/SuperSplat's quantised PLY "
    "(16 bytes a Gaussian + 3 per SH coefficient).",
)
@click.option(
    "--sh-degree",
    type=click.IntRange(0, 3),
    default=None,
    help="Keep the SH bands up to this degree (default: all the model has; .splat keeps 0).",
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
    help="Output path (default WS/runs/RUN/export/ splat.ply | scene.splat | scene.compressed.ply).",
)
@json_option
def command(workspace, run, fmt, sh_degree, frame, output, as_json):
    """Export a Gaussian-splat run -> WS/runs/RUN/export/ (files common splat viewers open).
    An antialiased run's opacities are written with their compensation averaged over the
    training views, since viewers do not compensate."""
    from recon.export.stage import export_splats

    result = export_splats(Workspace.open(workspace), run, frame, output, fmt, sh_degree)
    if as_json:
        emit_json(result)
    else:
        click.echo(
            f"export: {result['gaussians']} Gaussians ({frame} frame, {fmt}, SH degree "
            f"{result['sh_degree']}, {result['bytes'] / 1e6:.1f} MB) -> {result['path']}"
            + (
                "; antialiasing compensation baked into the opacities"
                if result["antialias_baked"]
                else ""
            )
        )
