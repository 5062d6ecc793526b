"""`recon run`: the whole pipeline in one command (sfm -> train -> render -> mesh -> eval), each
stage skipped when the workspace records it done and fresh, as make would."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import click

from recon.cli.common import emit_json, json_option, workspace_option
from recon.models.registry import METHOD_NAMES
from recon.workspace import Workspace
from recon.workspace.workspace import WorkspaceError

# sfm's exit code when fewer than --min-registered of the photos registered (the model is
# written and usable): the pipeline goes on and `recon run` exits with it at the end
PARTIAL_SFM = 3


def stage_commands(
    photos: Path | None, ws: Path, method: str, run: str, budget: float, frames: int, eval_args
) -> list[tuple[str, list[str]]]:
    """(workspace stage key, recon arguments) of each stage, in order."""
    w = ["-w", str(ws)]
    stages = []
    if photos is not None:
        stages.append(("sfm", ["sfm", str(photos), *w]))
    train = ["train", *w, "--method", method, "--run", run, "--force"]
    stages.append((f"train/{run}", [*train, "--time-budget", str(budget)] if budget else train))
    stages.append((f"render/{run}/test", ["render", *w, "--run", run]))
    if frames:
        orbit = ["render", *w, "--run", run, "--path", "orbit", "--frames", str(frames), "--video"]
        stages.append((f"render/{run}/orbit", orbit))
    stages.append((f"mesh/{run}", ["mesh", *w, "--run", run]))
    stages.append((f"eval/{run}", ["eval", *w, "--run", run, *eval_args]))
    return stages


def current_stages(ws_root: Path, photos: Path | None) -> set[str]:
    """The stages the workspace records as done and fresh (the sfm stage only if made from
    `photos`). One `status()`, which hashes every recorded input: it holds until a stage runs,
    and after that `recon run` reruns everything anyway."""
    if not (ws_root / Workspace.JSON_NAME).exists():
        return set()
    ws = Workspace.open(ws_root)
    current = set()
    for key, state in ws.status().items():
        if state["state"] != "done":
            continue
        if key == "sfm" and photos is not None:
            made_from = {ws.resolve(label).resolve() for label in state.get("inputs", {})}
            if photos.resolve() not in made_from:
                continue
        current.add(key)
    return current


@click.command()
@click.argument("photos", metavar="[PHOTOS|VIDEO]", required=False, type=click.Path(path_type=Path))
@workspace_option
@click.option(
    "--method",
    "-m",
    default="3dgs",
    show_default=True,
    type=click.Choice(METHOD_NAMES),
    help="What `recon train` trains.",
)
@click.option("--run", default=None, help="Run name (default: the method name).")
@click.option(
    "--time-budget",
    default=600.0,
    show_default=True,
    type=click.FloatRange(0),
    help="Training seconds (0: the method's own step count).",
)
@click.option(
    "--orbit-frames",
    default=120,
    show_default=True,
    type=click.IntRange(0),
    help="Frames of the orbit video (0 = no video).",
)
@click.option("--gt-poses", type=click.Path(exists=True, path_type=Path), help="For eval.")
@click.option("--gt-mesh", type=click.Path(exists=True, path_type=Path), help="For eval.")
@click.option("--force", is_flag=True, help="Run every stage, done or not.")
@json_option
def command(
    photos, workspace, method, run, time_budget, orbit_frames, gt_poses, gt_mesh, force, as_json
):
    """Photos or a video to a report in one command: sfm -> train -> render (the held-out views
    and an orbit video) -> mesh -> eval.

    \b
    recon run PHOTOS|VIDEO -w WS [--method M] [--time-budget S]
    recon run -w WS --method ngp          # another method on the workspace's poses

    A stage the workspace records as done and fresh is skipped, unless one before it ran (as
    make would; `recon status -w WS` shows the records). Each stage is the `recon` command of
    its name, run as you would run it; one that fails stops the pipeline with its exit code. A
    partial sfm (fewer than --min-registered of the photos registered: exit 3) goes on with
    what registered and `recon run` exits 3 at the end. Prints the report's path.
    """
    root = Path(workspace)
    if photos is None and not (root / "sfm" / "cameras.json").exists():
        raise click.UsageError(f"{root} has no sfm output: give the PHOTOS or VIDEO to start from")
    if photos is not None and not photos.exists():
        raise WorkspaceError(f"photo folder or video {photos} does not exist")
    run = run or method
    eval_args = [
        a
        for flag, p in (("--gt-poses", gt_poses), ("--gt-mesh", gt_mesh))
        if p
        for a in (flag, str(p))
    ]
    stages = stage_commands(photos, root, method, run, time_budget, orbit_frames, eval_args)
    done, code, rerun = [], 0, force
    current = set() if force else current_stages(root, photos)
    for key, args in stages:
        if not rerun and key in current:
            done.append({"stage": key, "ran": False})
            if not as_json:
                click.echo(f"run: {key} is done and fresh: skipped", err=True)
            continue
        rerun = True  # everything after a stage that ran is rebuilt on its output
        if not as_json:
            click.echo(f"run: recon {' '.join(args)}", err=True)
        # with --json the stages' own output goes to stderr (fd 2), so stdout holds one JSON
        stdout = 2 if as_json else None
        result = subprocess.run(
            [sys.executable, "-m", "recon.cli", *args], check=False, stdout=stdout
        )
        done.append({"stage": key, "ran": True, "exit_code": result.returncode})
        if result.returncode == PARTIAL_SFM and key == "sfm":
            code = PARTIAL_SFM
        elif result.returncode != 0:
            click.echo(f"error: recon {args[0]} failed (exit {result.returncode})", err=True)
            sys.exit(result.returncode)
    report = root / "report.html"
    if as_json:
        emit_json({"workspace": str(root), "run": run, "stages": done, "report": str(report)})
    else:
        click.echo(f"report: {report}")
    sys.exit(code)
