"""Where a training step's time goes: `torch.profiler` over a few steps of one method on a
workspace, after an untimed warm-up (so an Instant-NGP occupancy grid has left its warm-up and
3D Gaussians have densified). Prints and writes (JSON) per step: wall ms, the device's kernel
time, kernel launches, host syncs and device-to-host copies, and the ops and kernels that take
the most time. On a GPU this says whether a step is bound by the GPU's arithmetic (kernel time
close to wall), by launches (many launches, kernel time far below wall) or by syncs. Runs on a
CPU too (CPU activity only: the op counts and their host times).

    python pipelines/gpu_profile.py -w WS --method ngp [--device cuda] [--warmup 400]
        [--steps 20] [--downscale 1] [--preset auto] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile

from recon.models.registry import method_spec
from recon.train.config import resolve_preset
from recon.train.trainer import Trainer
from recon.workspace import Workspace
from recon.workspace.scene import load_scene, load_train_data

# runtime calls counted per step, by what they cost a GPU step
LAUNCHES = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx")
SYNCS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize")
COPIES = ("cudaMemcpyAsync", "cudaMemcpy")
HOST_READS = ("aten::item", "aten::_local_scalar_dense", "aten::nonzero")


def device_time_us(event) -> float:
    """An event's self time on the device in microseconds (the attribute was renamed in torch 2.4)."""
    for name in ("self_device_time_total", "self_cuda_time_total"):
        if hasattr(event, name):
            return float(getattr(event, name))
    return 0.0


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def profile_steps(trainer, data, device: torch.device, first: int, steps: int) -> dict:
    """`steps` training steps from step `first` under the profiler -> per-step figures."""
    activities = [ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(ProfilerActivity.CUDA)
    sync(device)
    t0 = time.perf_counter()
    with profile(activities=activities) as prof:
        for step in range(first, first + steps):
            trainer.step(data, step)
        sync(device)
    wall = time.perf_counter() - t0
    averages = prof.key_averages()
    count = lambda names: sum(e.count for e in averages if e.key in names) / steps
    # the kernels themselves: ops and labelled regions (`record_function`) also carry the
    # device time of what they launched, and would count it twice
    kernels = [
        e
        for e in averages
        if e.device_type == DeviceType.CUDA and not getattr(e, "is_user_annotation", False)
    ]
    top_ops = sorted(
        (e for e in averages if e.key.startswith("aten::")),
        key=lambda e: e.self_cpu_time_total,
        reverse=True,
    )[:15]
    top_kernels = sorted(kernels, key=device_time_us, reverse=True)[:15]
    return {
        "wall_ms_per_step": round(1e3 * wall / steps, 3),
        "kernel_ms_per_step": round(sum(device_time_us(e) for e in kernels) / 1e3 / steps, 3),
        "launches_per_step": count(LAUNCHES),
        "syncs_per_step": count(SYNCS),
        "copies_per_step": count(COPIES),
        "host_reads_per_step": {
            k: sum(e.count for e in averages if e.key == k) / steps for k in HOST_READS
        },
        "aten_ops_per_step": sum(e.count for e in averages if e.key.startswith("aten::")) / steps,
        "top_ops_cpu_ms_per_step": {
            e.key: [round(e.self_cpu_time_total / 1e3 / steps, 3), e.count // steps]
            for e in top_ops
        },
        "top_kernels_ms_per_step": {
            e.key[:80]: [round(device_time_us(e) / 1e3 / steps, 3), e.count // steps]
            for e in top_kernels
        },
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-w", "--workspace", type=Path, required=True)
    ap.add_argument("--method", required=True)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--preset", default="auto")
    ap.add_argument("--downscale", type=int, default=1)
    ap.add_argument("--warmup", type=int, default=400, help="untimed steps first")
    ap.add_argument("--steps", type=int, default=20, help="steps under the profiler")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    device = torch.device(args.device)
    ws = Workspace(args.workspace)
    scene = load_scene(ws)
    spec = method_spec(args.method)
    preset, _ = resolve_preset(args.preset, spec.presets, device.type)
    model = spec.build(spec.config_cls(**spec.presets.get(preset, {})), scene.info).to(device)
    data = load_train_data(ws, scene, "train", device, args.downscale)
    model.train()
    trainer = Trainer(model)
    half = args.warmup // 2
    for step in range(args.warmup):
        if step == half:
            sync(device)
            t0 = time.perf_counter()
        trainer.step(data, step)
    sync(device)
    warm_ms = 1e3 * (time.perf_counter() - t0) / max(1, args.warmup - half) if args.warmup else None
    result = {
        "method": args.method,
        "preset": preset,
        "device": str(device),
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "image_size": list(data.images.shape[1:3]),
        "warmup_steps": args.warmup,
        "wall_ms_per_step_unprofiled": None if warm_ms is None else round(warm_ms, 3),
        "stats": {k: float(v) for k, v in model.stats().items()},
        **profile_steps(trainer, data, device, args.warmup, args.steps),
    }
    text = json.dumps(result, indent=1)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
