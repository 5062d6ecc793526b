"""`recon train`: fit nerf / ngp / plenoxel / 3dgs to the workspace's scene."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import click

from recon.cli.common import emit_json, json_option, workspace_option
from recon.cli.progress import Progress
from recon.models.registry import METHOD_NAMES, method_spec
from recon.train.config import TrainConfig, field_help
from recon.train.stage import train
from recon.workspace import Workspace


def _list_options(method: str) -> str:
    spec = method_spec(method)
    helps = field_help(spec.config_cls)
    lines = [f"options of --method {method} (set with --set KEY=VALUE); presets: {', '.join(spec.presets)}"]
    for f in dataclasses.fields(spec.config_cls):
        lines.append(f"  {f.name} = {f.default!r}  {helps.get(f.name, '')}")
    return "\n".join(lines)


@click.command("train")
@workspace_option
@click.option("--method", "-m", required=True, type=click.Choice(METHOD_NAMES),
              help="Scene representation to train.")
@click.option("--run", "run", default=None, help="Run name (default: the method name).")
@click.option("--preset", default="fast", show_default=True,
              help="fast: sized for a CPU; paper: the paper's settings (GPU-sized).")
@click.option("--steps", default=0, show_default=True, help="Stop after N steps (0: no limit).")
@click.option("--time-budget", "time_budget", default=0.0, show_default=True,
              help="Stop within this many seconds of wall time, evaluations included (0: no limit).")
@click.option("--max-side", default=0, show_default=True, type=click.IntRange(0),
              help="Train on images whose longer side is at most N px (0: chosen for the method and budget).")
@click.option("--downscale", default=0, show_default=True, type=click.IntRange(0),
              help="Train on the sfm images downscaled by K (0: chosen for the method and budget).")
@click.option("--patience", default=0, show_default=True,
              help="Stop when held-out PSNR has not improved for this many evaluations (0: off).")
@click.option("--eval-every", default=30.0, show_default=True,
              help="Seconds of training between held-out PSNR evaluations (the speed-vs-error curve).")
@click.option("--eval-views", default=4, show_default=True, help="Held-out views used for that PSNR.")
@click.option("--checkpoint-every", default=60.0, show_default=True, help="Seconds between checkpoints.")
@click.option("--seed", default=0, show_default=True)
@click.option("--threads", default=0, show_default=True, help="CPU threads (0: all cores).")
@click.option("--device", default="auto", type=click.Choice(["auto", "cpu", "cuda"]), show_default=True)
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="Override a method option (repeatable); see --list-options.")
@click.option("--init-from-ply", "init_ply", default=None,
              type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="3dgs: start from this INRIA splat PLY (world units, as `recon export` writes).")
@click.option("--list-options", is_flag=True, help="List the method's options with their help and exit.")
@click.option("--resume", is_flag=True, help="Continue an interrupted run from its last checkpoint.")
@click.option("--force", is_flag=True, help="Overwrite an existing run / train on a stale sfm stage.")
@json_option
def command(workspace, method, run, preset, steps, time_budget, max_side, downscale, patience,
            eval_every, eval_views, checkpoint_every, seed, threads, device, overrides, init_ply,
            list_options, resume, force, as_json):
    """Train a scene representation -> WS/runs/RUN/ (run.json, log.jsonl, checkpoints/, model.pt).

    Without --steps, --time-budget or --patience the method's own step count applies.
    Ctrl-C saves a checkpoint; `--resume` continues from it.
    """
    spec = method_spec(method)
    if list_options:
        click.echo(_list_options(method))
        return
    if max_side and downscale:
        raise click.UsageError("give --max-side or --downscale, not both")
    if init_ply is not None:
        if not spec.starts_from_splats:
            raise click.UsageError(f"--init-from-ply is for methods that start from splats (3dgs), not {method}")
        overrides = (*overrides, f"init_ply={init_ply.resolve()}")
    ws = Workspace.open(workspace)
    if not (steps or time_budget or patience):
        steps = int(getattr(spec.config_cls(**spec.presets.get(preset, {})), "default_steps", 0)) or 0
        if not steps:
            raise click.UsageError("give --steps, --time-budget or --patience")
    cfg = TrainConfig(method=method, preset=preset, steps=steps, time_budget_s=time_budget,
                      seed=seed, max_side=max_side, downscale=downscale, eval_every_s=eval_every,
                      eval_views=eval_views, patience=patience, checkpoint_every_s=checkpoint_every,
                      threads=threads, device=device)
    run = run or method
    with Progress(enabled=not as_json) as progress:
        summary = train(ws, run, cfg, list(overrides), resume, force, log_fn=progress.log,
                        progress=progress)
    if as_json:
        emit_json(summary)
    else:
        psnr = summary["best_test_psnr"]
        res = summary["resolution"]["working"]
        click.echo(f"train: run '{run}' {summary['steps']} steps at {res['width']}x{res['height']} "
                   f"in {summary['elapsed_s']:.1f} s ({summary['train_wall_s']:.1f} s of steps; "
                   f"stopped: {summary['stop_reason']}); held-out PSNR "
                   f"{'n/a' if psnr is None else f'{psnr:.2f} dB'} -> {ws.run_dir(run)}")
