"""Speed and cost of a run from its run.json and log.jsonl."""

from __future__ import annotations

import json
from pathlib import Path


def read_log(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(ln) for ln in path.read_text().splitlines() if ln.strip()]


def psnr_curve(log: list[dict]) -> list[tuple[float, float]]:
    """(training seconds, held-out PSNR) points logged during training."""
    return [(e["wall_s"], e["test_psnr"]) for e in log if "test_psnr" in e]


def time_to_psnr(curve: list[tuple[float, float]], level: float) -> float | None:
    """First training time at which the held-out PSNR reached `level` dB (None if never)."""
    return next((t for t, p in curve if p >= level), None)


def speed_metrics(run_doc: dict, log: list[dict]) -> dict:
    curve = psnr_curve(log)
    wall = run_doc.get("train_wall_s") or (log[-1]["wall_s"] if log else None)
    steps = run_doc.get("steps")
    return {
        "train_wall_s": wall,
        "time_budget_s": (run_doc.get("train") or {}).get("time_budget_s") or None,
        "steps": steps,
        "steps_per_s": round(steps / wall, 3) if steps and wall else None,
        "time_to_psnr_s": {str(lv): time_to_psnr(curve, lv) for lv in (20, 25, 30)},
        "peak_rss_mb": run_doc.get("peak_rss_mb"),
        "parameters": (run_doc.get("model_stats") or {}).get("parameters"),
        "model_bytes": run_doc.get("model_bytes"),
        "stop_reason": run_doc.get("stop_reason"),
        "elapsed_s": run_doc.get("elapsed_s"),
        "trained_at": _trained_size(run_doc),
    }


def _trained_size(run_doc: dict) -> list[int] | None:
    working = (run_doc.get("resolution") or {}).get("working")
    return [working["width"], working["height"]] if working else None
