"""`make bench` (after bench.py): how fast each trained lego-200 run renders, at its training size
(200 x 200) and at 4x (800 x 800, `recon render --scale 4`), with the model's size on disk and
the render process's peak memory. Results as JSON + a markdown table in bench/results/.

Protocol: the runs bench.py left in bench/work/lego-200 (one per method, named after it), every
25th test view (8 frames), `OMP_NUM_THREADS=2`; frames/s from the median time per frame that
`recon render` measures (model load and PNG/EXR writing excluded); peak RSS of the whole
`recon render` process (ru_maxrss of a child that runs only it). The PSNR column is each run's
`recon eval` (every 8th test view, as bench.py) where it has one.

The neural fields (ngp, nerf) are also baked into a plenoxel lattice and trained on for
`--bake-budget` seconds (`recon train --method plenoxel --bake-from RUN`, run RUN-baked,
made again only when RUN is newer), evaluated, and rendered the same way: how fast the same
scene renders once baked, and at what PSNR against the run it came from.

    python pipelines/bench_render.py [--methods 3dgs,ngp] [--scales 1,4] [--bakes ngp,nerf]
"""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import socket
import subprocess
import sys
from pathlib import Path

import click

ROOT = Path(__file__).resolve().parents[1]
WS = ROOT / "bench" / "work" / "lego-200"
METHODS = ("3dgs", "ngp", "plenoxel", "nerf")
BAKES = ("ngp", "nerf")  # runs of these methods are also baked into a plenoxel lattice
BAKE_BUDGET_S = 120
EVERY = 25


def recon(*args: str) -> None:
    """A `recon` command in a child process with 2 threads; its error ends the benchmark."""
    proc = subprocess.run(
        [sys.executable, "-m", "recon.cli", *args],
        capture_output=True,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "2"},
        cwd=ROOT,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"recon {' '.join(args)} failed:\n{proc.stderr[-2000:]}")


def bake(ws: Path, run: str, budget: float) -> str:
    """RUN-baked: `run` baked into a plenoxel lattice, trained on for `budget` seconds and
    evaluated on every 8th test view; made again only when `run`'s model is newer."""
    baked = f"{run}-baked"
    source, done = ws / "runs" / run / "model.pt", ws / "runs" / baked / "model.pt"
    if not done.exists() or done.stat().st_mtime < source.stat().st_mtime:
        print(f"bench render: baking {run} ({budget:g} s) ...", flush=True)
        recon(
            "train", "-w", str(ws), "--method", "plenoxel", "--bake-from", run,
            "--time-budget", f"{budget:g}", "--threads", "2", "--eval-every", f"{budget / 4:g}",
            "--eval-views", "4", "--force",
        )  # fmt: skip
        recon("eval", "-w", str(ws), "--run", baked, "--every", "8", "--no-pictures")
    return baked


def eval_psnr(ws: Path, run: str) -> float | None:
    """The mean PSNR of the run's last `recon eval`, if it has one."""
    path = ws / "runs" / run / "eval" / "metrics.json"
    return json.loads(path.read_text())["mean"]["psnr"] if path.exists() else None


def render_once(ws: Path, run: str, scale: float) -> dict:
    """`recon render` of every EVERY-th test view at `scale` in a child process -> its JSON
    result plus the child's peak RSS (MB)."""
    wrapper = (
        "import json, resource, subprocess, sys;"
        "p = subprocess.run(sys.argv[1:], capture_output=True, text=True);"
        "sys.stderr.write(p.stderr);"
        "print(json.dumps({'rc': p.returncode, 'out': p.stdout,"
        " 'peak_kb': resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}))"
    )
    cmd = [
        sys.executable, "-c", wrapper, sys.executable, "-m", "recon.cli", "render",
        "-w", str(ws), "--run", run, "--every", str(EVERY), "--scale", f"{scale:g}", "--json",
    ]  # fmt: skip
    proc = subprocess.run(
        cmd,
        capture_output=True,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "2"},
        cwd=ROOT,
        check=False,
    )
    wrapped = json.loads(proc.stdout)
    if wrapped["rc"] != 0:
        raise RuntimeError(f"recon render {run} --scale {scale} failed:\n{proc.stderr[-2000:]}")
    result = json.loads(wrapped["out"])
    return {**result, "peak_rss_mb": round(wrapped["peak_kb"] / 1024, 1)}


def markdown(results: dict) -> str:
    lines = [
        f"# recon render throughput {results['date']} on {results['machine']}",
        "",
        (
            f"lego-200 runs of bench/work/lego-200, every {EVERY}th test view, 2 threads; load "
            f"average at start {results['load_average']}."
        ),
        "",
        "| method | run | test PSNR | model MB | size | ms / frame (median) | frames/s | peak RSS MB |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results["runs"]:
        psnr = "–" if r.get("test_psnr") is None else f"{r['test_psnr']:.2f}"
        for s in r["scales"]:
            w, h = s["resolution"]
            lines.append(
                f"| {r['method']} | {r['run']} | {psnr} | {r['model_mb']:.1f} | {w}×{h} | "
                f"{s['ms_per_frame_median']:.1f} | {1000 / s['ms_per_frame_median']:.2f} | "
                f"{s['peak_rss_mb']:.0f} |"
            )
    return "\n".join(lines) + "\n"


@click.command()
@click.option("--methods", default=",".join(METHODS), show_default=True)
@click.option(
    "--scales", default="1,4", show_default=True, help="Output sizes x the training size."
)
@click.option(
    "--bakes",
    default=",".join(BAKES),
    show_default=True,
    help="Runs to also bake into a plenoxel lattice ('' = none).",
)
@click.option("--bake-budget", default=BAKE_BUDGET_S, show_default=True, type=float)
@click.option("--workspace", default=str(WS), show_default=True)
@click.option("--out-dir", default=str(ROOT / "bench" / "results"), show_default=True)
def main(
    methods: str, scales: str, bakes: str, bake_budget: float, workspace: str, out_dir: str
) -> None:
    ws = Path(workspace)
    runs = [m for m in methods.split(",") if (ws / "runs" / m / "model.pt").exists()]
    missing = sorted(set(methods.split(",")) - set(runs))
    if missing:
        print(f"bench render: no trained run for {', '.join(missing)} in {ws} (run bench.py)")
    runs += [bake(ws, run, bake_budget) for run in bakes.split(",") if run in runs]
    results = {
        "date": dt.date.today().isoformat(),
        "machine": f"{socket.gethostname()}-{platform.machine()}-{os.cpu_count()}cpu",
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "bake_budget_s": bake_budget,
        "runs": [],
    }
    for run in runs:
        doc = json.loads((ws / "runs" / run / "run.json").read_text())
        entry = {
            "run": run,
            "method": doc["method"] + (" (baked)" if doc["config"].get("bake_from") else ""),
            "model_mb": (ws / "runs" / run / "model.pt").stat().st_size / 1e6,
            "test_psnr": eval_psnr(ws, run),
            "scales": [],
        }
        for scale in (float(s) for s in scales.split(",")):
            print(f"bench render: {run} at x{scale:g} ...", flush=True)
            entry["scales"].append({"scale": scale, **render_once(ws, run, scale)})
        results["runs"].append(entry)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"{results['date']}-{results['machine']}-render"
    (out / f"{stem}.json").write_text(json.dumps(results, indent=2) + "\n")
    (out / f"{stem}.md").write_text(markdown(results))
    print(markdown(results))


if __name__ == "__main__":
    main()
