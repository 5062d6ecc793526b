"""`recon render`: test views or a camera path of a trained run."""

from __future__ import annotations

import click

from recon.cli.common import emit_json, json_option, workspace_option
from recon.cli.progress import Progress
from recon.options import config_option, from_options
from recon.render.stage import RenderConfig, render_run
from recon.workspace import Workspace


@click.command("render")
@workspace_option
@click.option("--run", required=True, help="Run to render (see `recon status`).")
@config_option(RenderConfig, "split")
@config_option(RenderConfig, "path")
@config_option(RenderConfig, "frames")
@config_option(RenderConfig, "video")
@config_option(RenderConfig, "fps")
@config_option(RenderConfig, "max_side", type=click.IntRange(0))
@config_option(RenderConfig, "downscale", type=click.IntRange(0))
@config_option(RenderConfig, "scale", type=click.FloatRange(0, min_open=True))
@config_option(RenderConfig, "every", type=click.IntRange(1))
@config_option(RenderConfig, "device")
@click.option("--force", is_flag=True, help="Render even if the run is stale.")
@json_option
def command(workspace, run, force, as_json, **options):
    """Render RGB PNGs, metric depth EXRs (channel Z, original units) and optionally an MP4
    -> WS/runs/RUN/renders/<split or path>/."""
    if options["max_side"] and options["downscale"]:
        raise click.UsageError("give --max-side or --downscale, not both")
    ws = Workspace.open(workspace)
    cfg = from_options(RenderConfig, options)
    with Progress(enabled=not as_json) as progress:
        result = render_run(ws, run, cfg, force, progress)
    if as_json:
        emit_json(result)
    else:
        w, h = result["resolution"]
        first = (
            f"; the first took {result['ms_first_frame']:.0f} ms"
            if result["frames"] > 1 and result["ms_first_frame"] > 2 * result["ms_per_frame_median"]
            else ""
        )  # kernels compiled or loaded from their cache on first use
        click.echo(
            f"render: {result['frames']} frames of {w}x{h} at "
            f"{result['ms_per_frame_median']:.1f} ms/frame (median{first}) -> {result['out']}"
        )
