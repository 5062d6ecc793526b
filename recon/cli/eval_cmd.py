"""`recon eval`: metrics per run and a report comparing all runs."""

from __future__ import annotations

import click

from recon.cli.common import emit_json, json_option, workspace_option
from recon.cli.progress import Progress
from recon.eval.stage import EvalConfig, evaluate
from recon.workspace import Workspace


@click.command("eval")
@workspace_option
@click.option("--run", "runs", multiple=True, help="Run(s) to evaluate (default: every trained run).")
@click.option("--split", default="test", show_default=True, help="Held-out split.")
@click.option("--every", default=1, show_default=True, help="Evaluate every N-th view of the split.")
@click.option("--gt-mesh", default="", help="Ground-truth mesh (original units); default: the dataset's.")
@click.option("--gt-points", default="", help="Ground-truth point cloud (original units).")
@click.option("--tau", default=0.0, show_default=True,
              help="F-score threshold in original units (0: 1 % of the GT bounding-box diagonal).")
@click.option("--gt-poses", default="", help="Reference poses (transforms.json or COLMAP model) for sfm accuracy.")
@click.option("--no-lpips", is_flag=True, help="Skip LPIPS.")
@click.option("--max-side", default=0, show_default=True, type=click.IntRange(0),
              help="Evaluate at the pyramid level whose longer side fits N px (0: each run's training level).")
@click.option("--downscale", default=0, show_default=True, type=click.IntRange(0),
              help="Evaluate at the sfm images downscaled by K (0: each run's training level).")
@click.option("--device", default="auto", type=click.Choice(["auto", "cpu", "cuda"]), show_default=True)
@click.option("--force", is_flag=True, help="Evaluate stale runs too.")
@json_option
def command(workspace, runs, split, every, gt_mesh, gt_points, tau, gt_poses, no_lpips, max_side,
            downscale, device, force, as_json):
    """Evaluate runs -> WS/runs/RUN/eval/metrics.json, WS/report.md, WS/speed_vs_error.png."""
    if max_side and downscale:
        raise click.UsageError("give --max-side or --downscale, not both")
    ws = Workspace.open(workspace)
    cfg = EvalConfig(split=split, every=every, gt_mesh=gt_mesh, gt_points=gt_points, tau=tau,
                     gt_poses=gt_poses, lpips=not no_lpips, max_side=max_side, downscale=downscale,
                     device=device)
    with Progress(enabled=not as_json) as progress:
        results = evaluate(ws, list(runs), cfg, force, progress)
    if as_json:
        emit_json(results)
        return
    if "sfm" in results:
        p = results["sfm"]["pose"]
        click.echo(f"eval: sfm poses vs {p['reference']}: {p['matched']} matched, median rotation error "
                   f"{p['median_rotation_error_deg']:.3f} deg, median centre error {p['median_center_error_pct']:.3f} % "
                   f"of the diagonal -> {ws.sfm_dir / 'pose_accuracy.json'}")
        return
    for run, m in results.items():
        mean = m["mean"]
        lp = f"{mean['lpips']:.4f}" if "lpips" in mean else "unavailable"
        geo = m["geometry"]
        g = (f", Chamfer {geo['chamfer']:.4g}, F-score {geo['fscore']:.3f}" if geo.get("status") == "ok" else "")
        w, h = m["resolution"]
        click.echo(f"eval: {run} at {w}x{h}: PSNR {mean['psnr']:.2f} dB (border {mean['psnr_border']:.2f}), "
                   f"SSIM {mean['ssim']:.4f}, LPIPS {lp}{g}")
    click.echo(f"report: {ws.report_md}  plot: {ws.speed_plot}")
