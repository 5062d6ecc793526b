"""`recon eval`: metrics per run and a report comparing all runs."""

from __future__ import annotations

import click

from recon.cli.common import emit_json, json_option, workspace_option
from recon.cli.progress import Progress
from recon.eval.stage import EvalConfig, evaluate
from recon.options import config_option, from_options
from recon.workspace import Workspace
from recon.workspace.workspace import MVS_RESULT


@click.command("eval")
@workspace_option
@click.option(
    "--run", "runs", multiple=True, help="Run(s) to evaluate (default: every trained run)."
)
@config_option(EvalConfig, "split")
@config_option(EvalConfig, "every")
@config_option(EvalConfig, "gt_mesh")
@config_option(EvalConfig, "gt_points")
@config_option(EvalConfig, "tau")
@config_option(EvalConfig, "gt_poses")
@config_option(EvalConfig, "lpips")
@config_option(EvalConfig, "max_side", type=click.IntRange(0))
@config_option(EvalConfig, "downscale", type=click.IntRange(0))
@config_option(EvalConfig, "photo_size")
@config_option(EvalConfig, "border", type=click.FloatRange(0.0, 0.5, min_open=True))
@config_option(EvalConfig, "mvs")
@config_option(EvalConfig, "pictures")
@config_option(EvalConfig, "viewer")
@config_option(EvalConfig, "device")
@click.option("--force", is_flag=True, help="Evaluate stale runs too.")
@json_option
def command(workspace, runs, force, as_json, **options):
    """Evaluate runs -> WS/runs/RUN/eval/metrics.json, WS/report.html, WS/report.md, WS/speed_vs_error.png."""
    if options["max_side"] and options["downscale"]:
        raise click.UsageError("give --max-side or --downscale, not both")
    ws = Workspace.open(workspace)
    cfg = from_options(EvalConfig, options)
    with Progress(enabled=not as_json) as progress:
        results = evaluate(ws, list(runs), cfg, force, progress)
    if as_json:
        emit_json(results)
        return
    if "sfm" in results:
        p = results["sfm"]["pose"]
        click.echo(
            f"eval: sfm poses vs {p['reference']}: {p['matched']} matched, median rotation error "
            f"{p['median_rotation_error_deg']:.3f} deg, median centre error {p['median_center_error_pct']:.3f} % "
            f"of the diagonal -> {ws.pose_accuracy_json}"
        )
        return
    for run, m in results.items():
        if run == MVS_RESULT:
            geo = m["geometry"]
            click.echo(
                f"eval: mvs mesh: Chamfer {geo['chamfer']:.4g}, F-score {geo['fscore']:.3f}"
                if geo.get("status") == "ok"
                else f"eval: mvs mesh: {geo['status']}"
            )
            continue
        mean = m["mean"]
        lp = f"{mean['lpips']:.4f}" if "lpips" in mean else "unavailable"
        geo = m["geometry"]
        g = (
            f", Chamfer {geo['chamfer']:.4g}, F-score {geo['fscore']:.3f}"
            if geo.get("status") == "ok"
            else ""
        )
        w, h = m["resolution"]
        click.echo(
            f"eval: {run} at {w}x{h}: PSNR {mean['psnr']:.2f} dB (border {mean['psnr_border']:.2f}), "
            f"SSIM {mean['ssim']:.4f}, LPIPS {lp}{g}"
        )
    if set(results) - {MVS_RESULT}:
        click.echo(
            f"report: {ws.report_html} (terminal: {ws.report_md.name}, plot: {ws.speed_plot.name})"
        )
