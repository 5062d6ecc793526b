"""A/B of nerf renders with and without early ray termination on one trained run: median ms a
frame and mean PSNR over every N-th test view, each variant timed twice, interleaved (a
measurement, not a test: it asserts nothing).

    python pipelines/bench_nerf_termination.py --workspace bench/work/lego-200 --run nerf
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time

import numba
import torch

from recon.workspace import Workspace
from recon.workspace.runs import load_run
from recon.workspace.scene import load_images


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workspace", required=True)
    parser.add_argument("--run", required=True)
    parser.add_argument("--every", type=int, default=8)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    numba.set_num_threads(args.threads)
    ws = Workspace.open(args.workspace)
    model, scene, _ = load_run(ws, args.run)
    idx = scene.split("test")[:: args.every]
    cameras, images = scene.cameras(idx, "cpu", 1), load_images(ws, scene, idx, 1)
    results: dict[str, list] = {"every sample": [], "early termination": []}
    renders: dict[str, list] = {}
    for name, eps in [("every sample", 0.0), ("early termination", 1e-4)] * 2:
        model.cfg = dataclasses.replace(model.cfg, eps_transmittance=eps)
        times, psnrs, rgbs = [], [], []
        for i in range(len(idx)):
            t0 = time.perf_counter()
            with torch.no_grad():
                rgb = model.render(cameras[i])["rgb"]
            times.append(time.perf_counter() - t0)
            mse = float(((rgb.clamp(0, 1) - images[i]) ** 2).mean())
            psnrs.append(-10 * math.log10(mse))
            rgbs.append(rgb)
        times.sort()
        results[name].append(
            {"median_ms": round(1000 * times[len(times) // 2], 1), "psnr": sum(psnrs) / len(psnrs)}
        )
        renders[name] = rgbs
    diff = max(
        float((a - b).abs().max())
        for a, b in zip(renders["every sample"], renders["early termination"])
    )
    print(json.dumps({**results, "views": len(idx), "max_pixel_difference": diff}))


if __name__ == "__main__":
    main()
