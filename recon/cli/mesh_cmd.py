"""`recon mesh`: a mesh of a trained run, in the original scene units."""

from __future__ import annotations

from pathlib import Path

import click

from recon.cli.common import emit_json, json_option, workspace_option
from recon.cli.progress import Progress
from recon.mesh.stage import MeshConfig, mesh_run
from recon.options import config_option, from_options
from recon.workspace import Workspace


@click.command("mesh")
@workspace_option
@click.option("--run", required=True, help="Run to mesh.")
@config_option(MeshConfig, "method")
@config_option(MeshConfig, "resolution")
@config_option(MeshConfig, "threshold")
@config_option(MeshConfig, "threshold_views")
@config_option(MeshConfig, "truncation")
@config_option(MeshConfig, "min_component")
@config_option(MeshConfig, "visible_only")
@config_option(MeshConfig, "visible_tolerance")
@config_option(MeshConfig, "format")
@config_option(MeshConfig, "previews", type=click.IntRange(0))
@config_option(MeshConfig, "preview_max_side", type=click.IntRange(16))
@config_option(MeshConfig, "device")
@click.option("--force", is_flag=True, help="Mesh even if the run is stale.")
@json_option
def command(workspace, run, force, as_json, **options):
    """Extract a mesh -> WS/runs/RUN/mesh/mesh.<format> (original scene units)."""
    ws = Workspace.open(workspace)
    cfg = from_options(MeshConfig, options)
    with Progress(enabled=not as_json) as progress:
        result = mesh_run(ws, run, cfg, force, progress)
    if as_json:
        emit_json(result)
    else:
        click.echo(
            f"mesh: {result['method']} {result.get('vertices')} vertices, {result.get('faces')} faces "
            f"in {result['seconds']:.1f} s -> {result['path']}"
        )
        if result["previews"]:
            where = Path(result["path"]).parent
            click.echo(f"mesh: previews -> {', '.join(str(where / n) for n in result['previews'])}")
