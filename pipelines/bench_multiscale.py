"""Rendering finer than the training size: the single-scale protocol of Mip-Splatting (Yu et
al. 2024: train at a single scale, test at several) on Blender lego.

`recon sfm --from-transforms nerf_synthetic_lego_400` (400 x 400), `recon train --method M
--downscale 4` (100 x 100, the run's training size) for a fixed number of steps (so the A/B
compares models, not the machine's load), then each of the 25 held-out views (test frames 0, 8,
..., 192) rendered at 1x, 2x and 4x the training size (100, 200, 400 px) and scored against the
photos at that size. Beside each direct render the training-size render upsampled (bicubic) to
the same size is scored: a model that renders at 2x or 4x no better than its upsampled 1x render
aliases (too-small splats that the training size never constrained, a dilation sized in
training pixels).

    python pipelines/bench_multiscale.py [--variants base,aa,f3d,mip] [--steps 3000] [--methods 3dgs]

Writes bench/results/<date>-multiscale.{json,md}; the runs stay in bench/work/lego-400.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import sys
from pathlib import Path

import click
import cv2
import numpy as np

from bench import ROOT, SHARED, git_commit, recon

TRAIN_DOWNSCALE = 4
SCALES = (4, 2, 1)  # pyramid levels: 1x, 2x, 4x the training size
EVERY = 8
# recon's option sets compared (--set KEY=VALUE); each a run named after its key
VARIANTS = {
    "base": [],
    "aa": ["antialiased=true"],
    "f3d": ["filter_3d=0.2"],
    "mip": ["antialiased=true", "filter_3d=0.2"],
}


def score(ws: Path, run: str, lpips_on: bool) -> dict:
    """PSNR / SSIM (/ LPIPS) of the direct render and of the upsampled training-size render at
    every level of SCALES, over the held-out views."""
    import torch

    from recon.metrics.image import psnr, ssim
    from recon.metrics.lpips import load_lpips, lpips
    from recon.render.views import render_view
    from recon.workspace import Workspace
    from recon.workspace.runs import load_run
    from recon.workspace.scene import load_images

    torch.set_num_threads(2)
    model, scene, _ = load_run(Workspace.open(ws), run, "cpu")
    idx = scene.split("test")[::EVERY]
    lp = load_lpips() if lpips_on else None
    low = {}
    out = {}
    for k in SCALES:
        cams = scene.cameras(idx, "cpu", k)
        gts = load_images(Workspace.open(ws), scene, idx, k)
        h, w = gts.shape[1:3]
        rows = {"direct": [], "upsampled": []}
        for i in range(len(idx)):
            pred = render_view(model, cams[i], w, h)["rgb"].clamp(0, 1).float()
            if k == TRAIN_DOWNSCALE:
                low[i] = pred.numpy()
            up = cv2.resize(low[i], (w, h), interpolation=cv2.INTER_CUBIC).clip(0, 1)
            for name, img in (("direct", pred), ("upsampled", torch.from_numpy(up))):
                m = {"psnr": float(psnr(img, gts[i])), "ssim": float(ssim(img, gts[i]))}
                if lp is not None:
                    m["lpips"] = float(lpips(img, gts[i], lp))
                rows[name].append(m)
        out[f"{w}px"] = {
            name: {key: float(np.mean([r[key] for r in rs])) for key in rs[0]}
            for name, rs in rows.items()
        }
        out[f"{w}px"]["gain_db"] = (
            out[f"{w}px"]["direct"]["psnr"] - out[f"{w}px"]["upsampled"]["psnr"]
        )
    return out


def markdown(doc: dict) -> str:
    lines = [
        f"# Rendering finer than the training size ({doc['date']}, {doc['host']}, commit {doc['commit']})",
        "",
        (
            f"lego-400, trained at 100 px for {doc['steps']} steps, 25 held-out views; `gain` = "
            "direct render PSNR minus the 100 px render upsampled (bicubic), at each size."
        ),
        "",
        "| method | variant | options | 100 px | 200 px direct / upsampled / gain | 400 px direct / upsampled / gain | LPIPS 400 px direct / upsampled |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in doc["runs"]:
        s = r["scores"]
        a, b, c = s["100px"], s["200px"], s["400px"]
        lines.append(
            f"| {r['method']} | {r['variant']} | {' '.join(r['options']) or 'defaults'} | "
            f"{a['direct']['psnr']:.2f} | {b['direct']['psnr']:.2f} / {b['upsampled']['psnr']:.2f} / "
            f"{b['gain_db']:+.2f} | {c['direct']['psnr']:.2f} / {c['upsampled']['psnr']:.2f} / "
            f"{c['gain_db']:+.2f} | {c['direct'].get('lpips', float('nan')):.4f} / "
            f"{c['upsampled'].get('lpips', float('nan')):.4f} |"
        )
    return "\n".join(lines) + "\n"


@click.command()
@click.option("--methods", default="3dgs")
@click.option("--variants", default=",".join(VARIANTS), help="3dgs option sets (VARIANTS)")
@click.option("--steps", default=3000, type=int)
@click.option("--lpips/--no-lpips", default=True)
@click.option("--out-dir", default=str(ROOT / "bench" / "results"))
def main(methods: str, variants: str, steps: int, lpips: bool, out_dir: str) -> None:
    ws = ROOT / "bench" / "work" / "lego-400"
    if not (ws / "sfm" / "cameras.json").exists():
        recon("sfm", "--from-transforms", str(SHARED / "nerf_synthetic_lego_400"), "-w", str(ws))
    doc = {
        "date": dt.date.today().isoformat(),
        "host": os.uname().nodename,
        "commit": git_commit(),
        "steps": steps,
        "runs": [],
    }
    for method in methods.split(","):
        for variant in variants.split(",") if method == "3dgs" else ["base"]:
            options = VARIANTS[variant] if method == "3dgs" else []
            run = f"ms-{method}-{variant}"
            sets = [a for o in options for a in ("--set", o)]
            train = recon(
                "train", "-w", str(ws), "--method", method, "--run", run, "--steps", str(steps),
                "--downscale", str(TRAIN_DOWNSCALE), "--threads", "2", "--force", *sets,
            )  # fmt: skip
            doc["runs"].append(
                {
                    "method": method,
                    "variant": variant,
                    "options": options,
                    "train_wall_s": train.get("train_wall_s"),
                    "scores": score(ws, run, lpips),
                }
            )
            print(json.dumps(doc["runs"][-1]), file=sys.stderr)
    out = Path(out_dir) / f"{doc['date']}-multiscale"
    out.with_suffix(".json").write_text(json.dumps(doc, indent=1))
    out.with_suffix(".md").write_text(markdown(doc))
    print(markdown(doc))


if __name__ == "__main__":
    main()
