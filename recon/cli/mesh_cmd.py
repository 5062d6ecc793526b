"""`recon mesh`: a mesh of a trained run, in the original scene units."""

from __future__ import annotations

import click

from recon.cli.common import emit_json, json_option, workspace_option
from recon.cli.progress import Progress
from recon.mesh.stage import MeshConfig, mesh_run
from recon.workspace import Workspace


@click.command("mesh")
@workspace_option
@click.option("--run", required=True, help="Run to mesh.")
@click.option("--method", "method", default="auto", show_default=True,
              type=click.Choice(["auto", "marching-cubes", "tsdf"]),
              help="auto: marching cubes on density (nerf/ngp/plenoxel), TSDF fusion of rendered depth (3dgs).")
@click.option("--resolution", default=256, show_default=True, help="Samples/voxels along the box's longest side.")
@click.option("--threshold", default=0.0, show_default=True,
              help="Marching-cubes density level (0: ln2 / voxel size, i.e. opacity 0.5 across one voxel, or "
                   "the median density at the surface of rendered training views if that is lower).")
@click.option("--truncation", default=0.02, show_default=True, help="TSDF truncation (fraction of the box side).")
@click.option("--min-component", default=0.02, show_default=True,
              help="Remove connected components with fewer than this fraction of the faces.")
@click.option("--format", "fmt", default="ply", show_default=True, type=click.Choice(["ply", "obj", "glb"]))
@click.option("--device", default="auto", type=click.Choice(["auto", "cpu", "cuda"]), show_default=True)
@click.option("--force", is_flag=True, help="Mesh even if the run is stale.")
@json_option
def command(workspace, run, method, resolution, threshold, truncation, min_component, fmt, device, force, as_json):
    """Extract a mesh -> WS/runs/RUN/mesh/mesh.<format> (original scene units)."""
    ws = Workspace.open(workspace)
    cfg = MeshConfig(method=method, resolution=resolution, threshold=threshold, truncation=truncation,
                     min_component=min_component, format=fmt, device=device)
    with Progress(enabled=not as_json) as progress:
        result = mesh_run(ws, run, cfg, force, progress)
    if as_json:
        emit_json(result)
    else:
        click.echo(f"mesh: {result['method']} {result.get('vertices')} vertices, {result.get('faces')} faces "
                   f"in {result['seconds']:.1f} s -> {result['path']}")
