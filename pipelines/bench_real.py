"""The `fox-real` benchmark: a real phone capture with the defaults, as a new user runs it.

Protocol, through the real `recon` CLI (2 CPU threads, nothing else running):
- `recon sfm ../shared/data/fox/images -w WS` (the project's own SfM; every 8th photo held out);
- per method and budget: `recon train -w WS --method M --time-budget B` and nothing else (the
  working resolution, coarse-to-fine, appearance and the rest are the defaults' choice);
- `recon eval -w WS --run RUN --downscale 4`: the 9 held-out photos, the full-resolution
  undistorted images `recon sfm` wrote and the renders both area-downsampled to a quarter
  (about 270 x 480); PSNR, SSIM, LPIPS, and PSNR on the outer 15 % band of each image (where the
  unbounded background shows);
- wall time of `recon train` as measured around the command (the budget must bound it), steps/s,
  peak memory, model size, the working resolution the run chose.

    python pipelines/bench_real.py [--methods 3dgs,ngp] [--budgets 120,300,600,1800] [--reuse]

Writes bench/results/<date>-<machine>-fox-real.{json,md} (partial results per run in
bench/results/partial/, reusable with --reuse).
"""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import socket
import sys
import time
from pathlib import Path

import click

from bench import git_commit, matmul_gflops, recon

ROOT = Path(__file__).resolve().parents[1]
FOX = ROOT.parent / "shared" / "data" / "fox"
EVAL_DOWNSCALE = 4
TARGETS = {"3dgs": {120: 27.0, 600: 32.0, 1800: 33.5}, "ngp": {600: 28.0, 1800: 30.0}}


def run_sfm(ws: Path) -> dict:
    if (ws / "sfm" / "cameras.json").exists():
        return json.loads((ws / "sfm" / "report.json").read_text()) | {"reused": True}
    t0 = time.perf_counter()
    out = recon("sfm", str(FOX / "images"), "-w", str(ws))
    return out | {"wall_s": round(time.perf_counter() - t0, 1)}


def bench_run(ws: Path, method: str, budget: int) -> dict:
    run = f"{method}-{budget}"
    started = {
        "commit": git_commit(),
        "started": dt.datetime.now().isoformat(timespec="seconds"),
        "load_average_before": os.getloadavg()[0],
    }
    t0 = time.perf_counter()
    train = recon(
        "train",
        "-w",
        str(ws),
        "--method",
        method,
        "--run",
        run,
        "--time-budget",
        str(budget),
        "--threads",
        "2",
        "--force",
    )
    wall = time.perf_counter() - t0
    ev = recon("eval", "-w", str(ws), "--run", run, "--downscale", str(EVAL_DOWNSCALE))[run]
    mean, sp = ev["mean"], ev["speed"]
    return {
        **started,
        "method": method,
        "budget_s": budget,
        "run": run,
        "train_command_wall_s": round(wall, 1),
        "elapsed_s": train.get("elapsed_s"),
        "working_resolution": train["resolution"]["working"],
        "steps": train["steps"],
        "steps_per_s": sp["steps_per_s"],
        "psnr": mean["psnr"],
        "ssim": mean["ssim"],
        "lpips": mean.get("lpips"),
        "psnr_border": mean["psnr_border"],
        "eval_resolution": ev["resolution"],
        "render_ms_per_frame": ev["render_ms_per_frame"],
        "peak_rss_mb": sp["peak_rss_mb"],
        "model_bytes": sp["model_bytes"],
        "model_stats": train.get("model_stats"),
        "config": train.get("config"),
        "per_view": ev["per_view"],
    }


def markdown(results: dict) -> str:
    sfm = results.get("sfm", {})
    sfm_time = "workspace reused" if sfm.get("reused") else f"{sfm.get('wall_s', 0):.0f} s"
    lines = [
        f"# fox-real {results['date']} on {results['machine']}",
        (
            f"matmul {results['matmul_gflops']:.1f} GFLOP/s (float32, 2 threads); load average at start "
            f"{[round(x, 2) for x in results['load_average']]}"
        ),
        "",
        (
            f"sfm: {sfm.get('images_registered', sfm.get('images', '?'))} images registered "
            f"({sfm_time}); held-out photos evaluated at 1/{EVAL_DOWNSCALE} of the sfm size."
        ),
        "",
        (
            "| method | budget s | train wall s | trained at | steps | steps/s | PSNR | SSIM | LPIPS | "
            "border PSNR | target | peak MB | model MB | commit | load before |"
        ),
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results["runs"]:
        if "error" in r:
            lines.append(f"| {r['method']} | {r['budget_s']} | failed: {r['error'][:80]} |")
            continue
        wr, lp = r["working_resolution"], r["lpips"]
        target = TARGETS.get(r["method"], {}).get(r["budget_s"])
        verdict = (
            "–" if target is None else f"{target:g} {'met' if r['psnr'] >= target else 'MISSED'}"
        )
        lines.append(
            " | ".join(
                [
                    f"| {r['method']}",
                    str(r["budget_s"]),
                    f"{r['train_command_wall_s']:.0f}",
                    f"{wr['width']}×{wr['height']} (1/{wr['downscale']})",
                    str(r["steps"]),
                    f"{r['steps_per_s']:.2f}",
                    f"{r['psnr']:.2f}",
                    f"{r['ssim']:.4f}",
                    "–" if lp is None else f"{lp:.4f}",
                    f"{r['psnr_border']:.2f}",
                    verdict,
                    f"{r['peak_rss_mb']:.0f}",
                    f"{(r['model_bytes'] or 0) / 1e6:.1f}",
                    r.get("commit", "?"),
                    f"{r.get('load_average_before', 0):.2f} |",
                ]
            )
        )
    return "\n".join(lines) + "\n"


@click.command()
@click.option("--methods", default="3dgs,ngp", show_default=True)
@click.option(
    "--budgets", default="120,300,600,1800", show_default=True, help="Training budgets (s)."
)
@click.option("--workspace", default=str(ROOT / "bench" / "work" / "fox-real"), show_default=True)
@click.option("--out-dir", default=str(ROOT / "bench" / "results"), show_default=True)
@click.option(
    "--reuse", is_flag=True, help="Reuse per-run results of an interrupted benchmark (partial/)."
)
def main(methods: str, budgets: str, workspace: str, out_dir: str, reuse: bool) -> None:
    date = dt.date.today().isoformat()
    machine = f"{socket.gethostname()}-{platform.machine()}-{os.cpu_count()}cpu"
    ws, out = Path(workspace), Path(out_dir)
    partial = out / "partial"
    partial.mkdir(parents=True, exist_ok=True)
    results = {
        "date": date,
        "machine": machine,
        "matmul_gflops": matmul_gflops(),
        "load_average": os.getloadavg(),
        "eval_downscale": EVAL_DOWNSCALE,
        "runs": [],
    }
    print("bench fox-real: sfm ...", file=sys.stderr, flush=True)
    results["sfm"] = {k: v for k, v in run_sfm(ws).items() if not isinstance(v, (list, dict))}
    for method in methods.split(","):
        for budget in (int(b) for b in budgets.split(",")):
            done = partial / f"fox-real-{method}-{budget}.json"
            if reuse and done.exists():
                results["runs"].append(json.loads(done.read_text()))
                continue
            print(f"bench fox-real: {method} {budget} s ...", file=sys.stderr, flush=True)
            try:
                r = bench_run(ws, method, budget)
                done.write_text(json.dumps(r, indent=1))
            except RuntimeError as e:
                r = {"method": method, "budget_s": budget, "error": str(e).splitlines()[-1]}
            results["runs"].append(r)
    (out / f"{date}-{machine}-fox-real.json").write_text(json.dumps(results, indent=1) + "\n")
    (out / f"{date}-{machine}-fox-real.md").write_text(markdown(results))
    print(markdown(results))


if __name__ == "__main__":
    main()
