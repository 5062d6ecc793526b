"""Training-loop configuration and method-config overrides (`--set key=value`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from recon.options import opt


@dataclass(frozen=True)
class TrainConfig:
    method: str  # nerf | ngp | plenoxel | 3dgs
    preset: str = opt(
        "auto",
        "auto: gpu (3dgs) or paper on a CUDA device, fast elsewhere; fast: sized for a CPU; "
        "paper: the paper's settings (GPU-sized; its step schedules fitted to a budget's planned "
        "steps); gpu (3dgs): paper with the real-capture options of fast; a method may have more "
        "(plenoxel: lean), listed by --list-options",
    )
    steps: int = opt(0, "stop after this many steps (0 = no step limit)")
    time_budget_s: float = opt(
        0.0,
        "stop within this many seconds of wall time, evaluations included (0 = no limit)",
        flag="--time-budget",
    )
    seed: int = opt(0, "seeds torch/numpy; same seed + threads + device = same run")
    max_side: int = opt(
        0,
        "train on images whose longer side is at most N px (0 = chosen for the method and budget)",
    )
    downscale: int = opt(
        0, "train on the sfm images downscaled by K (0 = chosen for the method and budget)"
    )
    eval_every_s: float = opt(
        30.0, "held-out PSNR every this many seconds of training time", flag="--eval-every"
    )
    eval_views: int = opt(4, "held-out views used for the periodic PSNR (evenly spaced test views)")
    eval_max_side: int = opt(
        256, "the periodic PSNR renders at most this longer side (cheap, and inside the budget)"
    )
    eval_max_fraction: float = opt(
        0.1,
        "a periodic PSNR waits while evaluations would take more than this fraction of the "
        "run's wall time, and stops after a view past which the rest would (0 = no cap); a "
        "slow renderer then evaluates less often",
    )
    patience: int = opt(0, "stop when held-out PSNR has not improved for this many evals (0 = off)")
    min_improvement_db: float = opt(0.05, "what counts as an improvement for `patience`")
    checkpoint_every_s: float = opt(
        60.0, "checkpoint interval in training seconds (and at the end)", flag="--checkpoint-every"
    )
    keep_checkpoints: int = opt(2, "older checkpoints are deleted")
    surface_points: str = opt(
        "off",
        "on: methods that can (sdf) also fit the surface points of `recon mvs` "
        "(WS/mvs/points.ply), which must have run and be fresh | off (10-min sdf, 2 threads: "
        "walnut Chamfer 9.1 -> 6.3 mm, F 0.07 -> 0.34 with them; sample_data F 0.982 -> 0.928)",
        choices=("on", "off"),
    )
    threads: int = opt(0, "torch CPU threads (0 = all cores)")
    device: str = opt(
        "auto", "auto (CUDA when available) | cpu | cuda", choices=("auto", "cpu", "cuda")
    )


def _parse_value(text: str, typ, default):
    kind = typ if isinstance(typ, type) else type(default)
    if kind is bool or isinstance(default, bool):
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"expected a boolean, got {text!r}")
    if isinstance(default, tuple):
        return tuple(type(default[0])(v) if default else float(v) for v in text.split(","))
    if isinstance(default, int):
        return int(float(text)) if float(text).is_integer() else int(text)
    if isinstance(default, float):
        return float(text)
    return text


def apply_overrides(cls, base: dict, overrides: list[str]) -> dict:
    """`key=value` strings -> updated field dict, validated against the dataclass `cls`."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    out = dict(base)
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"--set expects key=value, got {item!r}")
        key, value = item.split("=", 1)
        key = key.strip().replace("-", "_")
        if key not in fields:
            raise ValueError(f"unknown option {key!r} for {cls.__name__}; see --list-options")
        f = fields[key]
        default = out.get(key, f.default)
        try:
            out[key] = _parse_value(value.strip(), f.type, default)
        except ValueError as e:
            raise ValueError(f"--set {key}: {e}") from e
    return out


AUTO_PRESETS = {
    "cuda": ("gpu", "paper")
}  # device type -> what "auto" means there, the first a method has
CPU_PRESET = "fast"  # what "auto" means elsewhere, and where a method has none of the device's


def resolve_preset(preset: str, presets: dict, device_type: str) -> tuple[str, str]:
    """The preset a run uses and why: `preset` itself unless "auto", which on a CUDA device is
    the method's "gpu" preset (its reference settings with what real captures need, sized for
    a GPU) or else its "paper" one, and the CPU's "fast" one elsewhere. Example: ("auto", 3dgs's
    presets, "cuda") -> ("gpu", "auto: gpu on a cuda device"); ngp's -> "paper"; on "cpu" ->
    ("fast", "auto: fast on a cpu device")."""
    if preset != "auto":
        return preset, f"--preset {preset}"
    chosen = next((p for p in AUTO_PRESETS.get(device_type, ()) if p in presets), CPU_PRESET)
    return chosen, f"auto: {chosen} on a {device_type} device"


def build_config(cls, presets: dict, preset: str, overrides: list[str]):
    if preset not in presets:
        raise ValueError(f"unknown preset {preset!r} (choose from {', '.join(presets)})")
    return cls(**apply_overrides(cls, dict(presets[preset]), overrides))
