"""Gather a sweep's evaluations into one cross-scene table (CSV + markdown) and one
speed-vs-error plot per scene: the last rule of `pipelines/Snakefile`.

Each input is what `recon eval --run RUN --json` printed ({run: metrics}), saved by the sweep as
RESULTS/<scene>/eval/<run>.json.

    python pipelines/sweep_table.py --out RESULTS EVAL_JSON...
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import click

COLUMNS = [
    "scene",
    "run",
    "method",
    "budget_s",
    "trained_at",
    "steps",
    "train_wall_s",
    "psnr",
    "ssim",
    "lpips",
    "psnr_border",
    "chamfer",
    "fscore",
    "peak_rss_mb",
    "render_ms_per_frame",
]


def rows_from_eval(scene: str, doc: dict) -> list[dict]:
    """One row per run in a `recon eval --json` document."""
    rows = []
    for run, m in doc.items():
        sp, mean, geo = m.get("speed", {}), m.get("mean", {}), m.get("geometry", {})
        geo_ok = geo.get("status") == "ok"
        size = sp.get("trained_at")
        rows.append(
            {
                "scene": scene,
                "run": run,
                "method": m.get("method", ""),
                "budget_s": sp.get("time_budget_s"),
                "trained_at": f"{size[0]}x{size[1]}" if size else None,
                "steps": sp.get("steps"),
                "train_wall_s": sp.get("train_wall_s"),
                "psnr": mean.get("psnr"),
                "ssim": mean.get("ssim"),
                "lpips": mean.get("lpips"),
                "psnr_border": mean.get("psnr_border"),
                "chamfer": geo.get("chamfer") if geo_ok else None,
                "fscore": geo.get("fscore") if geo_ok else None,
                "peak_rss_mb": sp.get("peak_rss_mb"),
                "render_ms_per_frame": m.get("render_ms_per_frame"),
            }
        )
    return rows


def gather(paths: list[Path]) -> list[dict]:
    """Rows of every eval document, its scene read from the path (<scene>/eval/<run>.json),
    sorted by scene, method and training time."""
    rows = []
    for p in paths:
        rows += rows_from_eval(Path(p).parent.parent.name, json.loads(Path(p).read_text()))
    return sorted(rows, key=lambda r: (r["scene"], r["method"], r["train_wall_s"] or 0, r["run"]))


def _cell(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        if not math.isfinite(v):
            return str(v)
        return f"{v:.4f}" if abs(v) < 1 else f"{v:.2f}"
    return str(v)


def write_csv(rows: list[dict], path: Path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: "" if r[k] is None else r[k] for k in COLUMNS})


def markdown(rows: list[dict]) -> str:
    head = "| " + " | ".join(COLUMNS) + " |\n|" + "---|" * len(COLUMNS) + "\n"
    body = "".join("| " + " | ".join(_cell(r[k]) for k in COLUMNS) + " |\n" for r in rows)
    return "# recon sweep\n\n" + head + body


def plot_scene(rows: list[dict], scene: str, path: Path, workspace: Path | None = None) -> None:
    """Held-out PSNR against training wall time: per method, the final evaluations of its runs
    (markers, joined over the budgets), and behind them each run's PSNR as logged during
    training (a few held-out views at low resolution; from the workspace's runs/RUN/log.jsonl
    when `workspace` is given)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from recon.eval.speed import psnr_curve, read_log

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    for method in sorted({r["method"] for r in rows if r["scene"] == scene}):
        runs = [r for r in rows if r["scene"] == scene and r["method"] == method]
        pts = sorted(
            (r["train_wall_s"], r["psnr"]) for r in runs if r["train_wall_s"] and r["psnr"]
        )
        (line,) = ax.plot(*zip(*pts), marker="o", label=method) if pts else ax.plot([], [])
        for r in runs if workspace is not None else []:
            log = workspace / "runs" / r["run"] / "log.jsonl"
            curve = [(t, p) for t, p in psnr_curve(read_log(log)) if t > 0] if log.exists() else []
            if curve:
                ax.plot(*zip(*curve), lw=0.8, alpha=0.5, color=line.get_color())
    ax.set_xscale("log")
    ax.set_xlabel("training wall time (s, log scale)")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    ax.set_title(f"{scene}: speed vs error")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


@click.command()
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True)
@click.option(
    "--workspaces",
    type=click.Path(file_okay=False, path_type=Path),
    help="The folder of the scenes' workspaces (<scene>/): the plots add each run's logged curve.",
)
@click.argument("evals", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
def main(out: Path, workspaces: Path | None, evals: tuple[Path, ...]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    rows = gather(list(evals))
    write_csv(rows, out / "table.csv")
    (out / "table.md").write_text(markdown(rows))
    for scene in sorted({r["scene"] for r in rows}):
        ws = workspaces / scene if workspaces is not None else None
        plot_scene(rows, scene, out / f"{scene}_speed_vs_error.png", ws)
    click.echo(f"{len(rows)} runs -> {out / 'table.md'}")


if __name__ == "__main__":
    main()
