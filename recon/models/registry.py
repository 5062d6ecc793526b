"""The methods: which exist, where their modules are, and how a trained model is saved, rebuilt
and placed on a device. Stages and commands ask the registry and a model's declared
capabilities (`Model.has_density`, `Model.exports_splats`, `MethodSpec.starts_from_splats`),
never a method's name.

Importing this module is cheap (no torch): `recon --help` lists the methods from
`METHOD_MODULES` without importing them.
"""

from __future__ import annotations

import dataclasses
import importlib
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

    from recon.models.base import MethodSpec, Model, SceneInfo

# method name -> the module that registers it (`models.base.register`) when imported
METHOD_MODULES = {
    "nerf": "recon.models.nerf",
    "ngp": "recon.models.ngp",
    "plenoxel": "recon.models.plenoxel",
    "3dgs": "recon.models.splatting",
    "sdf": "recon.models.sdf",
}
METHOD_NAMES = list(METHOD_MODULES)
MODEL_SCHEMA_VERSION = 1  # the layout of a saved model file (`save_model`)


def import_methods() -> dict[str, MethodSpec]:
    """Import every method module so it registers itself -> {name: spec}. A module that fails
    to import is an error: a broken method must not silently vanish from the CLI."""
    from recon.models.base import METHODS

    for module in METHOD_MODULES.values():
        importlib.import_module(module)
    return METHODS


def method_spec(name: str) -> MethodSpec:
    if name not in METHOD_MODULES:
        raise ValueError(f"unknown method {name!r} (methods: {', '.join(METHOD_NAMES)})")
    importlib.import_module(METHOD_MODULES[name])
    from recon.models.base import METHODS

    return METHODS[name]


def choose_device(name: str, cuda_missing: str | None = None) -> tuple[torch.device, str]:
    """The device of `--device NAME` and why it was chosen: auto (CUDA when available, else
    CPU) | cpu | cuda (an error without a CUDA device). `cuda_missing`: what the method lacks
    on CUDA (`MethodSpec.cuda_missing`), which sends auto to the CPU and makes cuda an error.
    Example: "auto" on a machine with an H200 -> (cuda, "auto: CUDA available: NVIDIA H200");
    without CUDA -> (cpu, "auto: no CUDA device")."""
    import torch

    cuda = torch.cuda.is_available()
    if name == "auto":
        if cuda and cuda_missing:
            return torch.device(
                "cpu"
            ), f"auto: CUDA available, but this method needs {cuda_missing} there"
        if cuda:
            return torch.device("cuda"), f"auto: CUDA available: {torch.cuda.get_device_name(0)}"
        return torch.device("cpu"), "auto: no CUDA device"
    if name == "cuda" and not cuda:
        raise ValueError("--device cuda was asked for but no CUDA device is available")
    if name == "cuda" and cuda_missing:
        raise ValueError(f"--device cuda: this method needs {cuda_missing} on CUDA")
    return torch.device(name), f"--device {name}"


def pick_device(name: str) -> torch.device:
    """auto (CUDA when available, else CPU) | cpu | cuda (`choose_device`)."""
    return choose_device(name)[0]


def save_model(path: Path, method: str, method_cfg: dict, model: Model) -> Path:
    """The trained model as one file: its method, its config and its state."""
    from recon.io.atomic import save_torch

    save_torch(
        {
            "schema_version": MODEL_SCHEMA_VERSION,
            "method": method,
            "config": method_cfg,
            "state_dict": model.file_state(),
        },
        path,
    )
    return path


def load_model(path: Path, scene: SceneInfo, device: str | torch.device = "cpu") -> Model:
    """Rebuild a model saved by `save_model` for `scene`, in eval mode on `device`."""
    import torch

    saved = torch.load(path, map_location="cpu", weights_only=True)
    if saved.get("schema_version", 1) > MODEL_SCHEMA_VERSION:
        raise ValueError(
            f"{path} was written by a newer recon (model schema_version "
            f"{saved['schema_version']}): upgrade recon"
        )
    spec = method_spec(saved["method"])
    model = spec.build(spec.config_cls(**config_from_json(spec.config_cls, saved["config"])), scene)
    model.load_state_dict(saved["state_dict"])
    return model.to(device).eval()


def config_from_json(cls, d: dict) -> dict:
    """A config dict read back from JSON: lists become tuples where the field's default is one,
    and options the method no longer has (a run saved before they were removed) are dropped."""
    names = {f.name for f in dataclasses.fields(cls)}
    out = {k: v for k, v in d.items() if k in names}
    for f in dataclasses.fields(cls):
        if isinstance(f.default, tuple) and isinstance(out.get(f.name), list):
            out[f.name] = tuple(out[f.name])
    return out
