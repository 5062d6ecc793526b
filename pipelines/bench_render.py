"""`make bench` (after bench.py): how fast each trained lego-200 run renders, at its training size
(200 x 200) and at 4x (800 x 800, `recon render --scale 4`), with the model's size on disk and
the render process's peak memory. Results as JSON + a markdown table in bench/results/.

Protocol: the runs bench.py left in bench/work/lego-200 (one per method, named after it), every
25th test view (8 frames), `OMP_NUM_THREADS=2`; frames/s from the median time per frame that
`recon render` measures (model load and PNG/EXR writing excluded); peak RSS of the whole
`recon render` process (ru_maxrss of a child that runs only it).

    python pipelines/bench_render.py [--methods 3dgs,ngp] [--scales 1,4]
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
EVERY = 25


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
        "| method | run | model MB | size | ms / frame (median) | frames/s | peak RSS MB |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results["runs"]:
        for s in r["scales"]:
            w, h = s["resolution"]
            lines.append(
                f"| {r['method']} | {r['run']} | {r['model_mb']:.1f} | {w}×{h} | "
                f"{s['ms_per_frame_median']:.1f} | {1000 / s['ms_per_frame_median']:.2f} | "
                f"{s['peak_rss_mb']:.0f} |"
            )
    return "\n".join(lines) + "\n"


@click.command()
@click.option("--methods", default=",".join(METHODS), show_default=True)
@click.option(
    "--scales", default="1,4", show_default=True, help="Output sizes x the training size."
)
@click.option("--workspace", default=str(WS), show_default=True)
@click.option("--out-dir", default=str(ROOT / "bench" / "results"), show_default=True)
def main(methods: str, scales: str, workspace: str, out_dir: str) -> None:
    ws = Path(workspace)
    runs = [m for m in methods.split(",") if (ws / "runs" / m / "model.pt").exists()]
    missing = sorted(set(methods.split(",")) - set(runs))
    if missing:
        print(f"bench render: no trained run for {', '.join(missing)} in {ws} (run bench.py)")
    results = {
        "date": dt.date.today().isoformat(),
        "machine": f"{socket.gethostname()}-{platform.machine()}-{os.cpu_count()}cpu",
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "runs": [],
    }
    for run in runs:
        doc = json.loads((ws / "runs" / run / "run.json").read_text())
        entry = {
            "run": run,
            "method": doc["method"],
            "model_mb": (ws / "runs" / run / "model.pt").stat().st_size / 1e6,
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
