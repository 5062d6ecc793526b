"""Speed benchmark of the 3dgs CPU path (a measurement, not a test: it asserts nothing).

    python pipelines/bench_gaussians.py --gaussians 50000 --sizes 200 800 --out bench_3dgs.json
    python pipelines/bench_gaussians.py --workspace WS --warmup 600 --steps 40   # a real scene

For each image size: render forward and forward+backward ms per frame (projection + SH +
binning + rasterization), training steps/s of a 3dgs `Trainer.step` (SSIM loss, Adam, no
densification so the count stays put), and where one training step's time goes, from the
`3dgs.*` profiler labels the model and kernels carry. The scene: G Gaussians on a sphere
shell (radius 0.8, scales from the point spacing) seen from an orbit at distance 3.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numba
import torch
from torch.profiler import ProfilerActivity, profile

from recon.cameras import Cameras
from recon.gaussians.render import composite_rgb, composite_rgbd, project_splats
from recon.models.base import SceneInfo, TrainData
from recon.models.splatting import GaussianModel
from recon.models.splatting_config import PRESETS, GaussiansConfig
from recon.synthetic.splats import orbit_cameras, shell_gaussians
from recon.train.trainer import Trainer

LABELS = (
    "project",
    "rasterize",
    "bin",
    "raster_forward",
    "loss",
    "backward",
    "raster_backward",
    "project_backward",
    "optimizer",
    "densify",
)


def median_ms(fn, reps: int) -> float:
    fn()  # warm-up (numba compile or cache load)
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000 * statistics.median(times)


def bench_render(gaussians: dict, camera: Cameras, reps: int) -> dict[str, float]:
    """Forward (rgb + depth, no grad) and forward+backward (rgb, sum loss) ms per frame."""
    params = {k: v.clone().requires_grad_() for k, v in gaussians.items()}
    bg = torch.zeros(3)

    def forward():
        with torch.no_grad():
            composite_rgbd(project_splats(params, camera, 3), bg)

    def forward_backward():
        rgb, _ = composite_rgb(project_splats(params, camera, 3), bg)
        rgb.sum().backward()

    return {
        "forward_ms": median_ms(forward, reps),
        "forward_backward_ms": median_ms(forward_backward, reps),
    }


def training_setup(gaussians: dict, cameras: Cameras) -> tuple[GaussianModel, TrainData]:
    with torch.no_grad():
        images = torch.stack(
            [
                composite_rgb(project_splats(gaussians, cameras[i], 3), torch.zeros(3))[0]
                for i in range(len(cameras))
            ]
        )
    G = gaussians["means"].shape[0]
    gen = torch.Generator().manual_seed(1)
    scene = SceneInfo(
        aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]),
        unbounded=False,
        background=torch.zeros(3),
        near=0.1,
        far=6.0,
        points=gaussians["means"] + 0.01 * torch.randn(G, 3, generator=gen),
        point_colors=torch.rand(G, 3, generator=gen),
    )
    config = GaussiansConfig(**{**PRESETS["fast"], "densify_start": 10**9, "sh_degree_interval": 1})
    return GaussianModel(config, scene), TrainData(images.clamp(0, 1), cameras)


def bench_training(gaussians: dict, cameras: Cameras, steps: int) -> dict:
    """Steps/s of training at full SH degree, and its time split by `3dgs.*` labels (ms/step,
    measured under the profiler, which adds a little overhead)."""
    model, data = training_setup(gaussians, cameras)
    return profile_steps(Trainer(model), data, 3, steps)


def profile_steps(trainer: Trainer, data: TrainData, first: int, steps: int) -> dict:
    """Time `steps` train steps from step `first` (after one warm-up step), then profile as
    many more: steps/s, ms per `3dgs.*` label per step, the Gaussian count at the end."""
    trainer.step(data, first)
    t0 = time.perf_counter()
    for step in range(first + 1, first + 1 + steps):
        trainer.step(data, step)
    steps_per_s = steps / (time.perf_counter() - t0)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for step in range(first + 1 + steps, first + 1 + 2 * steps):
            trainer.step(data, step)
    totals = {e.key: e.cpu_time_total for e in prof.key_averages()}
    # the model's `3dgs.*` phases and the trainer's (`train.backward`, `train.optimizer`)
    split = {
        k: round((totals.get(f"3dgs.{k}", 0.0) + totals.get(f"train.{k}", 0.0)) / steps / 1000, 2)
        for k in LABELS
    }
    split["backward_other"] = round(
        split["backward"] - split["raster_backward"] - split["project_backward"], 2
    )
    labelled = sum(
        split[k] for k in ("project", "rasterize", "loss", "backward", "optimizer", "densify")
    )
    split["unlabelled"] = round(1000 / steps_per_s - labelled, 2)  # Python, logging, view pick
    return {
        "steps_per_s": round(steps_per_s, 3),
        "ms_per_step_profiled": split,
        "gaussians": trainer.model.num_gaussians,
    }


def bench_workspace(
    workspace: str, warmup: int, steps: int, overrides: list[str], downscale: int = 1
) -> dict:
    """Default (fast preset) training on a workspace's training views: `warmup` plain steps
    (densification on, so the count is what training really sees), then `profile_steps`."""
    from recon.train.config import build_config
    from recon.workspace import Workspace
    from recon.workspace.scene import load_scene, load_train_data

    ws = Workspace.open(workspace)
    scene = load_scene(ws)
    data = load_train_data(ws, scene, "train", downscale=downscale)
    config = build_config(GaussiansConfig, PRESETS, "fast", overrides)
    trainer = Trainer(GaussianModel(config, scene.info))
    t0 = time.perf_counter()
    for step in range(warmup):
        trainer.step(data, step)
    warm_s = time.perf_counter() - t0
    return {
        "workspace": workspace,
        "warmup_steps": warmup,
        "warmup_s": round(warm_s, 1),
        "size": [int(data.cameras.width[0]), int(data.cameras.height[0])],
        **profile_steps(trainer, data, warmup, steps),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--gaussians", type=int, default=50_000)
    parser.add_argument("--sizes", type=int, nargs="+", default=[200, 800])
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", default=None, help="also write the results to this JSON file")
    parser.add_argument("--workspace", default=None, help="profile training on this workspace")
    parser.add_argument("--warmup", type=int, default=600, help="--workspace: steps before timing")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        help="--workspace: override a config field, KEY=VALUE (repeatable)",
    )
    parser.add_argument(
        "--downscale", type=int, default=1, help="--workspace: train at 1/K of the sfm size"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    numba.set_num_threads(args.threads)
    if args.workspace:
        result = bench_workspace(
            args.workspace, args.warmup, args.steps, args.overrides, args.downscale
        )
        print(json.dumps(result), flush=True)
        if args.out:
            with open(args.out, "w") as f:
                json.dump(result, f, indent=2)
        return
    gaussians = shell_gaussians(args.gaussians)
    results = {"gaussians": args.gaussians, "threads": args.threads, "sizes": {}}
    for size in args.sizes:
        cameras = orbit_cameras(8, size)
        entry = bench_render(gaussians, cameras[0], args.reps)
        entry.update(bench_training(gaussians, cameras, args.steps))
        results["sizes"][str(size)] = entry
        print(json.dumps({str(size): entry}), flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(results, f, indent=2)


if __name__ == "__main__":
    main()
