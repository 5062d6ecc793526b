"""A volume model's training step makes no host round trip (issue #52, "recon on an NVIDIA GPU").

On a GPU a step must not read a tensor on the host (`.item()`, `float(t)`, `bool(t)`, `.cpu()`,
`.numpy()`, `.tolist()`, ...) nor make tensors on the host for the device (a factory without
`device=`, `torch.tensor` of host data): each waits for the GPU's queue or copies. There is no
GPU here, so `recon.devices.uses_cpu_kernels` is switched off, the torch twins (the path a GPU
takes) serve the CPU tensors, and a `TorchFunctionMode` records every such call that recon's
own code makes inside the step. Warm-up steps (the first builds grids and caches constants)
run unwatched; the watched steps are ordinary ones, with and without an occupancy update.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import pytest
import torch
from torch import Tensor
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten

import recon
from recon import devices
from tests.conftest import sphere_scene, train_step

RECON = str(Path(recon.__file__).parent)
# torch's own Python between a caller and the mode: the dispatch, and the Python-level wrappers
# of the functions watched (a call from torch's own code, e.g. the optimizers' reads of their
# CPU step counters, is torch's business)
DISPATCH = {str(Path(torch.__file__).parent / f) for f in ("overrides.py", "_tensor.py")}

READS = {
    Tensor.item,
    Tensor.tolist,
    Tensor.cpu,
    Tensor.numpy,
    Tensor.__bool__,
    Tensor.__float__,
    Tensor.__int__,
    Tensor.__index__,
    Tensor.__array__,
    torch.equal,
    torch.allclose,
    torch.is_nonzero,
}
FACTORIES = {
    torch.zeros,
    torch.ones,
    torch.empty,
    torch.full,
    torch.arange,
    torch.linspace,
    torch.logspace,
    torch.eye,
    torch.rand,
    torch.randn,
    torch.randint,
    torch.randperm,
}
HOST_DATA = {torch.tensor, torch.as_tensor, torch.asarray, Tensor.new_tensor}


def _caller() -> str | None:
    """file:line of the code that called the watched function, if it is recon's (this module's
    own calls are attributed to whoever called it: the planted leak of the last test)."""
    frame = sys._getframe(2)
    while frame is not None and (frame.f_code.co_filename in DISPATCH | {__file__}):
        frame = frame.f_back
    if frame is None or not frame.f_code.co_filename.startswith(RECON):
        return None
    return f"{frame.f_code.co_filename}:{frame.f_lineno}"


class HostRoundTrips(TorchFunctionMode):
    """Records (call, recon's file:line) of every host read or host-made tensor recon asks for,
    and of every use of `host_tensors`: tensors that stay on the host when a model moves to its
    device (its `SceneInfo`'s), which a step on a GPU would copy over at each use."""

    def __init__(self, host_tensors: tuple[Tensor, ...] = ()):
        super().__init__()
        self.host_ids = {id(t) for t in host_tensors}
        self.seen: list[tuple[str, str]] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        device = kwargs.get("device")
        named_cpu = [a for a in (*args[1:], device) if isinstance(a, str) and a.startswith("cpu")]
        host = (
            func in READS
            or (func in FACTORIES and (device is None or named_cpu))
            or (func in HOST_DATA and not (func is torch.as_tensor and isinstance(args[0], Tensor)))
            or (func is Tensor.to and named_cpu)
            or any(id(a) in self.host_ids for a in tree_flatten((args, kwargs))[0])
        )
        if host and (where := _caller()) is not None:
            self.seen.append((getattr(func, "__name__", str(func)), where))
        return func(*args, **kwargs)


@pytest.fixture
def torch_paths(monkeypatch):
    """The torch twins serve CPU tensors: the code path of a GPU."""
    monkeypatch.setattr(devices, "uses_cpu_kernels", lambda t: False)


def _with_alpha(data):
    """The sphere scene's views with an alpha channel (1 on the sphere), for random backgrounds."""
    alpha = ((data.images - 1.0).abs().amax(-1) > 1e-6).float()
    return dataclasses.replace(data, alpha=alpha, _levels={})


def _nerf(info, data, unbounded):
    from recon.models.nerf import NeRFConfig, NeRFModel

    cfg = NeRFConfig(
        depth=2, width=32, skip_layer=1, pos_bands=3, n_coarse=8, n_fine=8, rays_per_batch=128,
        occupancy_res=16, occupancy_every=2, occupancy_warmup=1, precision="fp32",
    )  # fmt: skip
    return NeRFModel(cfg, info), data


def _ngp(info, data, unbounded):
    from recon.models.ngp import NGPConfig, NGPModel

    cfg = NGPConfig(
        log2_table_size=12, n_levels=4, n_max=64, rays_per_batch=128, samples_per_batch=4096,
        march_steps=64, occupancy_res=16, occupancy_every=2, occupancy_warmup=1,
        random_background="off" if unbounded else "on",
    )  # fmt: skip
    return NGPModel(cfg, info), data if unbounded else _with_alpha(data)


def _plenoxel(info, data, unbounded):
    from recon.models.plenoxel import PlenoxelConfig, PlenoxelModel

    cfg = PlenoxelConfig(
        resolutions=(16,), upsample_steps=(), rays_per_batch=256, samples_per_batch=1 << 13,
        occupancy_res=16, occupancy_every=2,
    )  # fmt: skip
    return PlenoxelModel(cfg, info), data


def _sdf(info, data, unbounded):
    from recon.models.sdf import SDFConfig, SDFModel

    cfg = SDFConfig(
        log2_table_size=10, n_levels=4, n_max=32, width=32, color_width=16, rays_per_batch=128,
        samples_per_batch=0, march_steps=64, occupancy_res=16, occupancy_every=2,
        occupancy_warmup=1, eikonal_points=64, mask_weight=0.1,
        random_background="off" if unbounded else "on", outer_volume="on" if unbounded else "off",
    )  # fmt: skip
    data = _with_alpha(data)
    data.surface_points = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1) * 0.5
    return SDFModel(cfg, info), data


MODELS = {
    "nerf": _nerf,
    "nerf-unbounded": _nerf,
    "ngp": _ngp,
    "ngp-unbounded": _ngp,
    "plenoxel": _plenoxel,
    "sdf": _sdf,
    "sdf-outer": _sdf,
}


def _scene(name: str):
    data, info = sphere_scene(n_cams=3, size=12)
    unbounded = name.endswith("unbounded")
    if unbounded:
        info = dataclasses.replace(info, unbounded=True, near=0.1, far=8.0)
    return MODELS[name](info, data, unbounded or name.endswith("outer"))


def _host_tensors(model) -> tuple[Tensor, ...]:
    """The model's `SceneInfo` tensors: they stay on the host when the model moves."""
    scene = model.scene
    return tuple(
        t for t in (scene.aabb, scene.background, scene.points, scene.point_colors) if t is not None
    )


def _watched_steps(model, data, warm_up: int, watched: range) -> list[tuple[str, str]]:
    torch.manual_seed(0)
    for step in range(warm_up):
        train_step(model, data, step)
    mode = HostRoundTrips(_host_tensors(model))
    with mode:
        for step in watched:
            train_step(model, data, step)
    return mode.seen


@pytest.mark.parametrize("name", sorted(MODELS))
def test_a_training_step_makes_no_host_round_trip(torch_paths, name):
    model, data = _scene(name)
    # steps 3 (ordinary) and 4 (an occupancy update after warm-up) are watched
    seen = _watched_steps(model, data, 3, range(3, 5))
    assert not seen, "host round trips in a training step:\n" + "\n".join(
        f"{call} at {where}" for call, where in sorted(set(seen))
    )


def test_ngp_termination_prepass_makes_no_host_round_trip(torch_paths):
    """ngp's second way to its samples (a density pre-pass without gradients, then
    `march_terminated`'s rounds), taken once termination drops most samples."""
    model, data = _scene("ngp")
    for step in range(3):
        train_step(model, data, step)
    model._kept_fraction = 0.0
    mode = HostRoundTrips(_host_tensors(model))
    with mode:
        train_step(model, data, 3)
    assert not mode.seen, mode.seen


def test_the_watch_catches_a_host_read(torch_paths, monkeypatch):
    """The mode does see a `.item()` planted in a step (and a factory with no device)."""
    model, data = _scene("ngp")
    sigma = model.field.sigma

    def leaky(x):
        out = sigma(x)
        out.sum().item()
        torch.zeros(1)
        return out

    monkeypatch.setattr(model.field, "sigma", leaky)
    seen = _watched_steps(model, data, 3, range(4, 5))  # step 4 updates the occupancy grid
    assert {call for call, _ in seen} >= {"item", "zeros"}


def test_generators_follow_the_model_to_its_device(monkeypatch):
    """`Model.to` hands the model's generators to `devices.generator_on` with the device of its
    tensors (a CUDA model draws its random numbers on the GPU); on their own device they stay."""
    from recon.models import base

    model, _ = _scene("ngp")
    g = model.generator
    model.cpu()
    assert model.generator is g and devices.generator_on(g, torch.device("cpu")) is g
    moved = torch.Generator().manual_seed(7)
    asked = []
    monkeypatch.setattr(base, "generator_on", lambda gen, dev: asked.append((gen, dev)) or moved)
    model.cpu()
    assert asked == [(g, torch.device("cpu"))] and model.generator is moved
