"""Benchmark the report's 3D viewer on a trained run: bytes on disk, load time and frames per
second in headless chromium on its software WebGL (SwiftShader: the CPU, no GPU).

    python pipelines/bench_viewer.py -w bench/work/fox-real --run 3dgs-1800 [--size 1280x720]

Writes the run's page (`recon view --run`'s WS/viewer/RUN.html), loads it, then renders
`--full-frames` frames of the held-out camera's view at rest at `--size`, then `--frames` while
orbiting it a little each frame (every frame re-sorts the splats, as an interactive orbit does,
at the level of detail the viewer chooses to keep a moving view at 20 frames a second; a pixel
read back ends each frame) and writes
bench/results/<date>-viewer-<workspace>-<run>.json and .md. Needs chromium and chromedriver
(`make browser`).
"""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import click

ROOT = Path(__file__).resolve().parents[1]
WARMUP = 5  # moving frames the level of detail takes to settle (not counted)
sys.path.insert(0, str(ROOT))  # tests.browser: the headless chromium of the browser tests

from recon.eval.viewer import run_page, scene_doc
from recon.io.atomic import atomic_write_json
from recon.workspace import Workspace, atomic_write_text


def gaussian_bytes(script: Path, doc: dict) -> int:
    """The bytes of a scene script that carry its Gaussians: the packed string (the script's
    third line, between its quotes) or the float32 arrays' base64."""
    splats = doc.get("splats") or {}
    if splats.get("encoding") == "pack":
        line = script.read_bytes().split(b"\n")[2]
        return len(line.split(b' = "', 1)[1]) - 2  # less the closing quote and semicolon
    keys = ("means", "cov", "opacity", "sh", "intervals")
    return sum(len(splats[k]) for k in keys if splats.get(k))


def measure(page: Path, run: str, width: int, height: int, frames: int, full_frames: int) -> dict:
    from tests.browser import chromium_driver, console_errors

    with chromium_driver(webgl=True) as driver:
        start = time.perf_counter()
        driver.get(page.resolve().as_uri())
        while not driver.execute_script("return window.reconViewersReady === true"):
            if time.perf_counter() - start > 300:
                raise RuntimeError("the viewer did not start within 5 minutes")
            time.sleep(0.05)
        load_ms = driver.execute_script("return window.reconViewersReadyMs")
        # the first frame, drawn: a pixel read back after the load
        first_ms = driver.execute_script(
            "const v = Object.values(window.reconViewers)[0]; if (!v) return null;"
            "const px = new Uint8Array(4); v.gl.readPixels(0, 0, 1, 1, v.gl.RGBA, v.gl.UNSIGNED_BYTE, px);"
            "return performance.now();"
        )
        driver.set_script_timeout(1800)
        seen = driver.execute_script(
            f"const v = window.reconViewers[{json.dumps(run)}];"
            "if (!v) return null;"
            f"v.setCamera(0); v.setSize({width}, {height});"
            # full frames: the view at rest
            f"const full = []; for (let i = 0; i < {full_frames}; i++) {{"
            "  const t0 = performance.now(); v.render(); full.push(performance.now() - t0); }"
            # moving frames: an orbit, each frame at the level of detail the last one allowed
            # (its own read-back of a pixel waits for it to be drawn)
            f"const moving = []; for (let i = 0; i < {frames}; i++) {{"
            "  const t0 = performance.now(); v.orbit(0.01, 0.0);"
            "  moving.push({ms: performance.now() - t0, ...v.drawn}); }"
            "return {full, moving};"
        )
        status = driver.execute_script("return document.querySelector('.recon-status').textContent")
        errors = console_errors(driver)
    if seen is None:
        raise RuntimeError(f"the viewer did not start: {status}")
    full = statistics.median(seen["full"])
    # the orbit's frames once the level of detail has settled (its first WARMUP adapt it)
    settled = seen["moving"][WARMUP:] or seen["moving"]
    moving = statistics.median(f["ms"] for f in settled)
    return {
        "load_ms": round(load_ms, 1),
        "first_frame_drawn_ms": round(first_ms, 1) if first_ms is not None else None,
        "full_frame_ms_median": round(full, 1),
        "full_fps": round(1000 / full, 2),
        "moving_frame_ms_median": round(moving, 1),
        "fps": round(1000 / moving, 2),
        "moving_scale_median": statistics.median(f["scale"] for f in settled),
        "moving_share_median": statistics.median(f["share"] for f in settled),
        "moving_gaussians_median": statistics.median(f["gaussians"] for f in settled),
        "moving_frames": seen["moving"],
        "full_frames_ms": seen["full"],
        "frames": frames,
        "size": [width, height],
        "status": status,
        "console_errors": errors,
    }


@click.command()
@click.option("-w", "--workspace", required=True, type=click.Path(file_okay=False))
@click.option("--run", required=True)
@click.option("--size", default="1280x720", show_default=True)
@click.option("--frames", default=40, show_default=True, help="moving frames (an orbit)")
@click.option("--full-frames", default=3, show_default=True, help="frames of the view at rest")
@click.option("--out-dir", default=str(ROOT / "bench" / "results"), show_default=True)
def main(workspace, run, size, frames, full_frames, out_dir):
    ws = Workspace.open(workspace)
    width, height = (int(x) for x in size.split("x"))
    page = run_page(ws, run)
    script = page.parent / f"{run}.js"
    doc = scene_doc(script)
    count = doc["splats"]["count"] if "splats" in doc else 0
    splat_bytes = gaussian_bytes(script, doc)
    result = {
        "workspace": str(ws.root),
        "run": run,
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()} {os.cpu_count()} cpu",
        "load_average": list(os.getloadavg()),
        "gaussians_shown": count,
        "gaussians": doc["splats"]["of"] if "splats" in doc else 0,
        "scene_bytes": script.stat().st_size,
        "gaussian_bytes": splat_bytes,
        # the Gaussians' own data, and the whole scene file (cameras and sfm points too)
        "bytes_per_gaussian": round(splat_bytes / count, 1) if count else None,
        "file_bytes_per_gaussian": round(script.stat().st_size / count, 1) if count else None,
        **measure(page, run, width, height, frames, full_frames),
    }
    name = f"{dt.date.today()}-viewer-{ws.root.name}-{run}"
    out = Path(out_dir)
    atomic_write_json(out / f"{name}.json", result)
    atomic_write_text(
        out / f"{name}.md",
        f"# The 3D viewer on {ws.root.name} / {run} ({result['date']})\n\n"
        f"Headless chromium, software WebGL (SwiftShader), {result['machine']}, load average "
        f"{result['load_average'][0]:.2f} at the start.\n\n"
        "| Gaussians shown (of) | scene file | bytes a Gaussian: its data (the whole file) | load "
        f"| at rest: frame at {width}x{height} (median of {full_frames}) | moving: frame, fps "
        f"(median of {frames - WARMUP}) | moving: drawn at | moving: Gaussians drawn |\n"
        "|---|---|---|---|---|---|---|---|\n"
        f"| {count:,} ({result['gaussians']:,}) | {result['scene_bytes'] / 1e6:.2f} MB | "
        f"{result['bytes_per_gaussian']} ({result['file_bytes_per_gaussian']}) | "
        f"{result['load_ms'] / 1000:.2f} s (first frame drawn "
        f"{result['first_frame_drawn_ms'] / 1000:.1f} s) | "
        f"{result['full_frame_ms_median']:.0f} ms ({result['full_fps']:.1f} fps) | "
        f"{result['moving_frame_ms_median']:.0f} ms, **{result['fps']:.1f} fps** | "
        f"{result['moving_scale_median']:.2f} x the size, upsampled | "
        f"{result['moving_gaussians_median']:,.0f} ({result['moving_share_median']:.0%}) |\n",
    )
    click.echo(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
