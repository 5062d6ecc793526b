"""`recon train`: fit nerf / ngp / plenoxel / 3dgs to the workspace's scene."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import click

from recon.cli.common import emit_json, json_option, workspace_option
from recon.cli.progress import Progress
from recon.models.registry import METHOD_NAMES, choose_device, method_spec
from recon.options import config_option, field_help, from_options
from recon.train.config import TrainConfig, resolve_preset
from recon.train.stage import train
from recon.workspace import Workspace
from recon.workspace.runs import load_run


def _list_options(method: str) -> str:
    spec = method_spec(method)
    helps = field_help(spec.config_cls)
    lines = [
        f"options of --method {method} (set with --set KEY=VALUE); presets: {', '.join(spec.presets)}"
    ]
    for f in dataclasses.fields(spec.config_cls):
        lines.append(f"  {f.name} = {f.default!r}  {helps.get(f.name, '')}")
    return "\n".join(lines)


def _bakeable_model(ws: Workspace, spec, run: str) -> tuple[Path, int]:
    """The model file of a finished run whose field `spec`'s method can bake, and the pyramid
    level it trained at; else an error."""
    if not spec.starts_from_fields:
        raise click.UsageError(
            f"--bake-from bakes a field into a voxel lattice: use it with --method plenoxel, "
            f"not {spec.name}"
        )
    model, _, run_doc = load_run(ws, run)
    if not model.has_radiance:
        raise ValueError(
            f"run '{run}' ({run_doc.get('method', '?')}) has no radiance field to bake: "
            "bake an ngp or nerf run"
        )
    return ws.model_path(run).resolve(), int(run_doc["resolution"]["working"]["downscale"])


@click.command("train")
@workspace_option
@click.option(
    "--method",
    "-m",
    required=True,
    type=click.Choice(METHOD_NAMES),
    help="Scene representation to train.",
)
@click.option("--run", "run", default=None, help="Run name (default: the method name).")
@config_option(TrainConfig, "preset")
@config_option(TrainConfig, "steps")
@config_option(TrainConfig, "time_budget_s")
@config_option(TrainConfig, "max_side", type=click.IntRange(0))
@config_option(TrainConfig, "downscale", type=click.IntRange(0))
@config_option(TrainConfig, "patience")
@config_option(TrainConfig, "min_improvement_db")
@config_option(TrainConfig, "eval_every_s")
@config_option(TrainConfig, "eval_views")
@config_option(TrainConfig, "eval_max_side", type=click.IntRange(16))
@config_option(TrainConfig, "eval_max_fraction", type=click.FloatRange(0.0, 1.0))
@config_option(TrainConfig, "checkpoint_every_s")
@config_option(TrainConfig, "keep_checkpoints", type=click.IntRange(1))
@config_option(TrainConfig, "seed")
@config_option(TrainConfig, "surface_points")
@config_option(TrainConfig, "threads")
@config_option(TrainConfig, "device")
@click.option(
    "--set",
    "overrides",
    multiple=True,
    metavar="KEY=VALUE",
    help="Override a method option (repeatable); see --list-options.",
)
@click.option(
    "--init-from-ply",
    "init_ply",
    default=None,
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="3dgs: start from this INRIA splat PLY (world units, as `recon export` writes).",
)
@click.option(
    "--bake-from",
    "bake_from",
    default=None,
    metavar="RUN",
    help="plenoxel: start from this ngp or nerf run, baked into the voxel lattice, and train on "
    "(a copy that renders at the lattice's speed; the run is called RUN-baked by default).",
)
@click.option(
    "--list-options", is_flag=True, help="List the method's options with their help and exit."
)
@click.option(
    "--resume", is_flag=True, help="Continue an interrupted run from its last checkpoint."
)
@click.option(
    "--force", is_flag=True, help="Overwrite an existing run / train on a stale sfm stage."
)
@json_option
def command(
    workspace,
    method,
    run,
    overrides,
    init_ply,
    bake_from,
    list_options,
    resume,
    force,
    as_json,
    **options,
):
    """Train a scene representation -> WS/runs/RUN/ (run.json, log.jsonl, checkpoints/, model.pt).

    Without --steps, --time-budget or --patience the method's own step count applies.
    Ctrl-C saves a checkpoint; `--resume` continues from it.
    """
    spec = method_spec(method)
    if list_options:
        click.echo(_list_options(method))
        return
    if options["max_side"] and options["downscale"]:
        raise click.UsageError("give --max-side or --downscale, not both")
    if init_ply is not None:
        if not spec.starts_from_splats:
            raise click.UsageError(
                f"--init-from-ply is for methods that start from splats (3dgs), not {method}"
            )
        overrides = (*overrides, f"init_ply={init_ply.resolve()}")
    ws = Workspace.open(workspace)
    if bake_from is not None:
        path, level = _bakeable_model(ws, spec, bake_from)
        overrides = (*overrides, f"bake_from={path}")
        if not (options["max_side"] or options["downscale"]):
            options["downscale"] = level  # the baked copy trains at the source's resolution
        run = run or f"{bake_from}-baked"
        if run == bake_from:
            raise click.UsageError("--bake-from RUN writes a new run: give another --run")
    # --device cuda without one, or without what the method needs there: an error, up front
    missing = spec.cuda_missing() if spec.cuda_missing else None
    device, _ = choose_device(options["device"], missing)
    if not (options["steps"] or options["time_budget_s"] or options["patience"]):
        preset, _ = resolve_preset(options["preset"], spec.presets, device.type)
        method_cfg = spec.config_cls(**spec.presets.get(preset, {}))
        options["steps"] = method_cfg.default_steps
        if not options["steps"]:
            raise click.UsageError("give --steps, --time-budget or --patience")
    cfg = from_options(TrainConfig, options, method=method)
    run = run or method
    with Progress(enabled=not as_json) as progress:
        summary = train(
            ws, run, cfg, list(overrides), resume, force, log_fn=progress.log, progress=progress
        )
    if as_json:
        emit_json(summary)
    else:
        psnr = summary["best_test_psnr"]
        res = summary["resolution"]["working"]
        click.echo(
            f"train: run '{run}' {summary['steps']} steps at {res['width']}x{res['height']} "
            f"in {summary['elapsed_s']:.1f} s ({summary['train_wall_s']:.1f} s of steps; "
            f"stopped: {summary['stop_reason']}); held-out PSNR "
            f"{'n/a' if psnr is None else f'{psnr:.2f} dB'} -> {ws.run_dir(run)}"
        )
