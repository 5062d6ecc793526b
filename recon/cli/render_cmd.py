"""`recon render`: test views or a camera path of a trained run."""

from __future__ import annotations

import click

from recon.cli.common import emit_json, json_option, workspace_option
from recon.cli.progress import Progress
from recon.render.stage import RenderConfig, render_run
from recon.workspace import Workspace


@click.command("render")
@workspace_option
@click.option("--run", required=True, help="Run to render (see `recon status`).")
@click.option("--split", default="test", show_default=True, type=click.Choice(["test", "train", "val"]),
              help="Dataset views to render (ignored with --path).")
@click.option("--path", "path_kind", default="", type=click.Choice(["", "orbit", "spiral", "interpolate"]),
              help="Render a camera path instead of dataset views.")
@click.option("--frames", default=60, show_default=True, help="Frames of the camera path.")
@click.option("--video", is_flag=True, help="Also write video.mp4.")
@click.option("--fps", default=30, show_default=True)
@click.option("--max-side", default=0, show_default=True, type=click.IntRange(0),
              help="Render at the pyramid level whose longer side fits N px (0: the run's training level).")
@click.option("--downscale", default=0, show_default=True, type=click.IntRange(0),
              help="Render at the sfm images' size divided by K (0: the run's training level).")
@click.option("--device", default="auto", type=click.Choice(["auto", "cpu", "cuda"]), show_default=True)
@click.option("--force", is_flag=True, help="Render even if the run is stale.")
@json_option
def command(workspace, run, split, path_kind, frames, video, fps, max_side, downscale, device, force,
            as_json):
    """Render RGB PNGs, metric depth EXRs (channel Z, original units) and optionally an MP4
    -> WS/runs/RUN/renders/<split or path>/."""
    if max_side and downscale:
        raise click.UsageError("give --max-side or --downscale, not both")
    ws = Workspace.open(workspace)
    cfg = RenderConfig(split=split, path=path_kind, frames=frames, video=video, fps=fps,
                       max_side=max_side, downscale=downscale, device=device)
    with Progress(enabled=not as_json) as progress:
        result = render_run(ws, run, cfg, force, progress)
    if as_json:
        emit_json(result)
    else:
        w, h = result["resolution"]
        click.echo(f"render: {result['frames']} frames of {w}x{h} at {result['ms_per_frame']:.1f} ms/frame "
                   f"-> {result['out']}")
