"""report.md (one table comparing every evaluated run) and speed_vs_error.png."""

from __future__ import annotations

import math

from recon.eval.speed import psnr_curve, read_log
from recon.workspace import Workspace, atomic_path, atomic_write_text
from recon.workspace.workspace import MVS_RESULT


def _fmt(v, nd=2) -> str:
    if v is None or v == "":
        return "–"
    if isinstance(v, str):
        return v
    if isinstance(v, float):
        return f"{v:.{nd}f}" if math.isfinite(v) else str(v)
    return str(v)


def _size(wh) -> str:
    return f"{wh[0]}×{wh[1]}" if wh else "–"


COLUMNS = (
    "run", "method", "trained at", "steps", "train s", "eval at", "PSNR", "border PSNR", "SSIM",
    "LPIPS", "photos' size", "PSNR / LPIPS there (1× upsampled)", "t→25 dB s", "render ms", "params", "peak MB", "Chamfer", "F-score", "depth absrel",
)  # fmt: skip


def photo_size_cells(m: dict) -> list[str]:
    """The photos' size and the scores there of the direct render and, in brackets, of the
    render at the size in "eval at" upsampled (`eval.stage.photo_size_metrics`); dashes when
    the views were scored at the photos' size."""
    at = m.get("photo_size")
    if not at:
        return ["–", "–"]
    d, u = at["mean"], at["upsampled"]
    lp = lambda x: f" / {_fmt(x['lpips'], 3)}" if "lpips" in x else ""
    return [
        _size(at["resolution"]),
        f"{_fmt(d.get('psnr'))}{lp(d)} ({_fmt(u.get('psnr'))}{lp(u)})",
    ]


def row_cells(run: str, m: dict) -> list[str]:
    """One run's metrics.json as the `COLUMNS` of the report tables (markdown and HTML)."""
    sp, geo, mean = m.get("speed", {}), m.get("geometry", {}), m.get("mean", {})
    ok = geo.get("status") == "ok"
    return [
        run,
        m.get("method", ""),
        _size(sp.get("trained_at")),
        _fmt(sp.get("steps")),
        _fmt(sp.get("train_wall_s"), 1),
        _size(m.get("resolution")),
        _fmt(mean.get("psnr")),
        _fmt(mean.get("psnr_border")),
        _fmt(mean.get("ssim"), 4),
        _fmt(mean.get("lpips"), 4),
        *photo_size_cells(m),
        _fmt((sp.get("time_to_psnr_s") or {}).get("25"), 1),
        _fmt(m.get("render_ms_per_frame"), 1),
        _fmt(int(sp["parameters"]) if sp.get("parameters") else None),
        _fmt(sp.get("peak_rss_mb"), 0),
        _fmt(geo.get("chamfer"), 5) if ok else "–",
        _fmt(geo.get("fscore"), 3) if ok else "–",
        _fmt(mean.get("depth_abs_rel"), 4),
    ]


def write_report(ws: Workspace, metrics: dict[str, dict]) -> None:
    rows = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    rows += ["| " + " | ".join(row_cells(run, m)) + " |" for run, m in sorted(metrics.items())]
    any_m = next((m for r, m in metrics.items() if r != MVS_RESULT), {})
    notes = [
        (
            f"- Image metrics on the held-out `{any_m.get('split', 'test')}` views at the size in 'eval at' "
            "(the photos area-downsampled to it; renders of a finer-trained run too); "
            f"{any_m.get('lpips_network', '')}. Border PSNR: the outer "
            f"{100 * any_m.get('border_fraction', 0.15):.0f} % of each side, where a capture's far background shows."
        ),
        (
            "- At the photos' size: the held-out views rendered at the size of the photos themselves "
            "when 'eval at' is coarser; in brackets the render at 'eval at' upsampled (bicubic) "
            "for comparison (a direct render below it aliases)."
        ),
        "- Geometry (Chamfer, F-score at τ) in the original scene units against the ground truth, when given.",
        "- PSNR certifies interpolation between the cameras, not geometry: read both columns.",
    ]
    if MVS_RESULT in metrics:
        notes.append(
            f"- `{MVS_RESULT}`: the mesh of `recon mvs` (multi-view stereo, no trained model), "
            "scored for geometry only; 'trained at' is its depth maps' size, 'train s' the stage's wall time."
        )
    pose = any_m.get("pose", {})
    if pose.get("status") == "ok":
        notes.append(
            f"- SfM poses vs reference ({pose['matched']} images): median rotation error "
            f"{pose['median_rotation_error_deg']:.3f}°, median centre error "
            f"{pose['median_center_error_pct']:.3f} % of the diagonal."
        )
    text = (
        "# recon report\n\n"
        + "\n".join(rows)
        + "\n\n"
        + "\n".join(notes)
        + "\n\n![speed vs error](speed_vs_error.png)\n"
    )
    atomic_write_text(ws.report_md, text)
    plot_speed_vs_error(ws, [r for r in metrics if r != MVS_RESULT])


def plot_speed_vs_error(ws: Workspace, runs: list[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    for run in runs:
        curve = [(t, p) for t, p in psnr_curve(read_log(ws.log_jsonl(run))) if t > 0]
        if curve:
            ax.plot(*zip(*curve), marker="o", ms=3, label=run)
    ax.set_xscale("log")
    ax.set_xlabel("training time (s, log scale; evaluation excluded)")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.grid(True, which="both", alpha=0.3)
    if ax.get_legend_handles_labels()[0]:  # runs trained without held-out PSNR draw nothing
        ax.legend()
    ax.set_title("speed vs error")
    fig.tight_layout()
    with atomic_path(ws.speed_plot) as tmp:
        fig.savefig(tmp)
    plt.close(fig)
