"""`make bench`: the lego-200 protocol for every method at its default CPU settings with a fixed
training-time budget, plus sfm on sample_data, fox and spiral-300 (300 photos at 800 x 600 that
`make_capture.py` renders with exact poses); results as JSON + a markdown table in bench/results/.

Protocol lego-200: `recon sfm --from-transforms nerf_synthetic_lego_400 --downscale 2`
(200x200, white background), train on the 100 train frames, test PSNR/SSIM/LPIPS on test
frames 0, 8, ..., 192, 2 CPU threads, wall time excluding evaluation. Everything runs through
the real `recon` CLI, as a user would.

    python pipelines/bench.py [--methods 3dgs,ngp,plenoxel,nerf] [--budget-scale 1.0] [--skip-sfm]
"""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import socket
import subprocess
import sys
import time
from pathlib import Path

import click

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
BUDGETS = {"3dgs": 600, "ngp": 600, "plenoxel": 600, "nerf": 1800}  # seconds, lego-200 protocol


def matmul_gflops(n: int = 1024, reps: int = 10) -> float:
    """The machine's float32 matmul GFLOP/s on 2 threads, to compare results across machines."""
    import torch

    torch.set_num_threads(2)
    a, b = torch.randn(n, n), torch.randn(n, n)
    a @ b
    t = time.perf_counter()
    for _ in range(reps):
        a @ b
    return 2 * n**3 * reps / (time.perf_counter() - t) / 1e9


def recon(*args: str) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "2"}
    proc = subprocess.run(
        [sys.executable, "-m", "recon.cli", *args, "--json"],
        check=False,
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"recon {' '.join(args)} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout)


def git_commit() -> str:
    """HEAD's short hash, with "+dirty" when tracked files differ (a result names its code)."""
    head = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"],
        check=False,
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    dirty = subprocess.run(
        ["git", "diff", "--quiet", "HEAD", "--", "recon", "pipelines"], check=False, cwd=ROOT
    ).returncode
    return (head.stdout.strip() or "unknown") + ("+dirty" if dirty else "")


def bench_method(ws: Path, method: str, budget: float) -> dict:
    started = {
        "commit": git_commit(),
        "started": dt.datetime.now().isoformat(timespec="seconds"),
        "load_average_before": os.getloadavg()[0],
    }
    train = recon(
        "train",
        "-w",
        str(ws),
        "--method",
        method,
        "--time-budget",
        str(budget),
        "--threads",
        "2",
        "--eval-every",
        str(max(budget / 10, 15)),
        "--eval-views",
        "4",
        "--force",
    )
    ev = recon("eval", "-w", str(ws), "--run", method, "--every", "8")[method]
    sp = ev["speed"]
    return {
        **started,
        "method": method,
        "time_budget_s": budget,
        "steps": train["steps"],
        "steps_per_s": sp["steps_per_s"],
        "test_psnr": ev["mean"]["psnr"],
        "test_ssim": ev["mean"]["ssim"],
        "test_lpips": ev["mean"].get("lpips"),
        "time_to_psnr_s": sp["time_to_psnr_s"],
        "render_ms_per_frame_200": ev["render_ms_per_frame"],
        "peak_rss_mb": sp["peak_rss_mb"],
        "parameters": sp["parameters"],
        "model_bytes": sp["model_bytes"],
        "model_stats": train.get("model_stats"),
        "stop_reason": train["stop_reason"],
        "psnr_curve": [(e["wall_s"], e["test_psnr"]) for e in _log(ws, method) if "test_psnr" in e],
    }


def _log(ws: Path, run: str) -> list[dict]:
    p = ws / "runs" / run / "log.jsonl"
    return [json.loads(ln) for ln in p.read_text().splitlines() if ln.strip()] if p.exists() else []


def markdown(results: dict) -> str:
    lines = [
        f"# recon benchmark {results['date']} on {results['machine']}",
        (
            f"matmul {results['matmul_gflops']:.1f} GFLOP/s (float32, 2 threads); load average at "
            f"start {results['load_average']}"
        ),
        "",
        "## lego-200",
        "",
        "| method | budget s | steps | steps/s | PSNR | SSIM | LPIPS | t→25 dB s | render ms/frame | peak MB | params | model MB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results["lego-200"]:
        if "error" in r:
            lines.append(f"| {r['method']} | failed: {r['error'][:80]} |")
            continue
        lp = r["test_lpips"]
        lines.append(
            " | ".join(
                [
                    f"| {r['method']}",
                    f"{r['time_budget_s']:.0f}",
                    str(r["steps"]),
                    f"{r['steps_per_s']:.2f}",
                    f"{r['test_psnr']:.2f}",
                    f"{r['test_ssim']:.4f}",
                    "–" if lp is None else f"{lp:.4f}",
                    str(r["time_to_psnr_s"].get("25")),
                    f"{r['render_ms_per_frame_200']:.0f}",
                    f"{r['peak_rss_mb']:.0f}",
                    str(int(r["parameters"] or 0)),
                    f"{(r['model_bytes'] or 0) / 1e6:.1f} |",
                ]
            )
        )
    lines += [
        "",
        "Each method's run (a `--reuse` table mixes runs): "
        + "; ".join(
            f"{r['method']} at {r.get('commit', '?')}, {r.get('started', '?')}, load "
            f"{r.get('load_average_before', '?')}"
            for r in results["lego-200"]
            if "error" not in r
        ),
    ]
    lines += [
        "",
        "Held-out PSNR during training (4 views, from log.jsonl) at 2 / 5 / 10 / 30 min:",
        "",
    ]
    for r in results["lego-200"]:
        if "error" not in r:
            at = [
                _psnr_at(r["psnr_curve"], t) if t <= r["time_budget_s"] * 1.02 else None
                for t in (120, 300, 600, 1800)
            ]
            lines.append(
                f"- {r['method']}: " + " / ".join("–" if p is None else f"{p:.2f}" for p in at)
            )
    sfm = {k[4:]: v for k, v in results.items() if k.startswith("sfm_")}
    if sfm:
        lines += [
            "",
            "## sfm (pycolmap through `run_sfm`, default options)",
            "",
            (
                "| scene | registered | median rot err ° | median centre err % diag | features s | matching s "
                "| mapping s | total wall s | load avg before |"
            ),
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for scene, r in sfm.items():
            acc, ph = r.get("accuracy_vs_reference", {}), r["phases"]["wall_s"]
            lines.append(
                f"| {scene} | {r['images_registered']}/{r['images_given']} | "
                f"{acc.get('median_rotation_error_deg')} | {acc.get('median_center_error_pct')} | "
                f"{ph.get('features')} | {ph.get('matching')} | {ph.get('mapping')} | "
                f"{r['total_wall_s']} | {r['load_average_1min_before_after'][0]} |"
            )
    return "\n".join(lines) + "\n"


def _psnr_at(curve: list, t: float) -> float | None:
    """The last held-out PSNR logged by training time t (None before the first). Evaluations are
    scheduled every budget/10 s and land up to a step later, hence the 2 s of slack."""
    before = [p for w, p in curve if w <= t + 2.0]
    return before[-1] if before else None


SPIRAL_CAPTURE = ROOT / "bench" / "work" / "data" / "spiral-300"


def ensure_spiral_capture() -> Path:
    """The spiral-300 capture's folder, rendered by make_capture.py unless complete (its
    transforms.json is written last; a partial render resumes)."""
    if not (SPIRAL_CAPTURE / "transforms.json").exists():
        print("bench: rendering the spiral-300 capture ...", file=sys.stderr, flush=True)
        script = ROOT / "pipelines" / "make_capture.py"
        subprocess.run(
            [sys.executable, str(script), "--out", str(SPIRAL_CAPTURE)], check=True, cwd=ROOT
        )
    return SPIRAL_CAPTURE


@click.command()
@click.option("--methods", default="3dgs,ngp,plenoxel,nerf", show_default=True)
@click.option(
    "--budget-scale", default=1.0, show_default=True, help="Scale every time budget (quick runs)."
)
@click.option("--skip-sfm", is_flag=True)
@click.option("--out-dir", default=str(ROOT / "bench" / "results"), show_default=True)
@click.option(
    "--reuse", is_flag=True, help="Reuse per-method results of an interrupted benchmark (partial/)."
)
def main(methods: str, budget_scale: float, skip_sfm: bool, out_dir: str, reuse: bool) -> None:
    from recon.models.registry import import_methods

    available = import_methods()
    date = dt.date.today().isoformat()
    machine = f"{socket.gethostname()}-{platform.machine()}-{os.cpu_count()}cpu"
    results = {
        "date": date,
        "machine": machine,
        "matmul_gflops": matmul_gflops(),
        "load_average": os.getloadavg(),
        "budget_scale": budget_scale,
        "lego-200": [],
    }
    ws = ROOT / "bench" / "work" / "lego-200"
    if not (ws / "sfm" / "cameras.json").exists():
        recon(
            "sfm",
            "--from-transforms",
            str(SHARED / "nerf_synthetic_lego_400"),
            "--downscale",
            "2",
            "-w",
            str(ws),
        )
    partial = Path(out_dir) / "partial"
    partial.mkdir(parents=True, exist_ok=True)
    for m in [m for m in methods.split(",") if m in available]:
        done = partial / f"lego-200-{m}.json"
        if reuse and done.exists():
            results["lego-200"].append(json.loads(done.read_text()))
            continue
        print(f"bench: {m} ...", file=sys.stderr, flush=True)
        try:
            r = bench_method(ws, m, BUDGETS[m] * budget_scale)
            done.write_text(json.dumps(r, indent=1))  # survives an interrupted benchmark
        except RuntimeError as e:
            r = {"method": m, "error": str(e).splitlines()[-1]}
        results["lego-200"].append(r)
    from recon.eval.report import plot_speed_vs_error
    from recon.workspace import Workspace

    plot_speed_vs_error(
        Workspace.open(ws), [r["method"] for r in results["lego-200"] if "error" not in r]
    )
    out_plot = Path(out_dir) / f"{date}-{machine}-speed_vs_error.png"
    out_plot.parent.mkdir(parents=True, exist_ok=True)
    out_plot.write_bytes((ws / "speed_vs_error.png").read_bytes())
    results["speed_vs_error_png"] = os.path.relpath(out_plot, ROOT)  # --out-dir may lie outside
    if not skip_sfm:
        spiral = ensure_spiral_capture()
        for scene, images, transforms in (
            ("sample", ROOT / "sample_data" / "images", ROOT / "sample_data" / "transforms.json"),
            ("fox", SHARED / "fox" / "images", SHARED / "fox" / "transforms.json"),
            ("spiral-300", spiral / "images", spiral / "transforms.json"),
        ):
            out = partial / f"sfm-{scene}.json"
            if not (reuse and out.exists()):
                print(f"bench: sfm {scene} ...", file=sys.stderr, flush=True)
                subprocess.run(
                    [
                        sys.executable,
                        str(ROOT / "pipelines" / "bench_sfm.py"),
                        "--images",
                        str(images),
                        "--transforms",
                        str(transforms),
                        "--out",
                        str(out),
                    ],
                    check=True,
                    cwd=ROOT,
                )
            results[f"sfm_{scene}"] = json.loads(out.read_text())
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{date}-{machine}.json").write_text(json.dumps(results, indent=1) + "\n")
    (out / f"{date}-{machine}.md").write_text(markdown(results))
    print(markdown(results))


if __name__ == "__main__":
    main()
