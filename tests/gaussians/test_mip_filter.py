"""The 3D smoothing filter (Mip-Splatting, Yu et al. 2024, Eqs. 8-10): sampling intervals,
the filtered scales and opacity against a brute-force convolution, gradients, and the model
with it on."""

import math

import torch

from recon.cameras import Cameras
from recon.gaussians.mip_filter import sampling_intervals, smoothed
from recon.models.splatting import GaussianModel
from tests.conftest import train_step
from tests.models.test_splatting import config, straight_and_resumed, synthetic_scene


def facing_cameras(distances, focal=100.0, size=64):
    """Cameras on the -z axis at `distances` from the origin, looking down +z (OpenCV)."""
    n = len(distances)
    cfw = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    cfw[:, 2, 3] = torch.tensor(distances, dtype=torch.float64)  # z_cam = z_world + d
    K = torch.tensor([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]], dtype=torch.float64)
    wh = torch.full((n,), size)
    return Cameras(K.expand(n, 3, 3).clone(), cfw, wh, wh.clone())


def test_sampling_interval_is_the_finest_over_the_cameras_that_see_the_point():
    cams = facing_cameras([2.0, 4.0])
    means = torch.tensor(
        [
            [0.0, 0.0, 0.0],  # seen by both: min(2, 4) / 100
            [0.8, 0.0, 0.0],  # near camera: u = 32 + 100 * 0.8 / 2 = 72 <= 1.15 * 64, seen
            [1.5, 0.0, 0.0],  # u = 107 for the near camera (outside), 69.5 for the far one
            [0.0, 0.0, -5.0],  # behind both
        ],
        dtype=torch.float64,
    )
    t = sampling_intervals(means, cams)
    assert torch.allclose(t[:3], torch.tensor([0.02, 0.02, 0.04], dtype=torch.float64))
    assert t[3] == t[:3].max()  # unseen: the largest interval of those seen


def test_smoothed_equals_a_brute_force_convolution():
    """An axis-aligned Gaussian alpha exp(-x^T Sigma^-1 x / 2) sampled on a grid and
    convolved (separably) with a unit-mass isotropic Gaussian of variance v: the peak is the
    filtered opacity and the second moments are the filtered squared scales."""
    scales = torch.tensor([0.05, 0.1, 0.2], dtype=torch.float64)
    interval, variance_scale = torch.tensor([0.1], dtype=torch.float64), 0.2  # v = 0.002
    alpha = 0.7
    log_s, logit = smoothed(
        torch.log(scales)[None],
        torch.logit(torch.tensor([alpha], dtype=torch.float64)),
        interval,
        variance_scale,
    )
    # worked example: coef = sqrt(0.0025 * 0.01 * 0.04 / (0.0045 * 0.012 * 0.042)) = 0.66402
    coef = math.sqrt(0.0025 * 0.01 * 0.04 / (0.0045 * 0.012 * 0.042))
    assert abs(coef - 0.66402) < 1e-5
    assert torch.allclose(torch.sigmoid(logit), torch.tensor([alpha * coef], dtype=torch.float64))
    v = variance_scale * 0.1**2
    h = 0.004
    x = torch.arange(-1.5, 1.5 + h / 2, h, dtype=torch.float64)
    kernel = torch.exp(-0.5 * x**2 / v)
    kernel = kernel / kernel.sum()
    peak = alpha
    for s in scales:  # separable: the 3D peak is the product of the 1D peaks
        g = torch.exp(-0.5 * x**2 / s**2)
        conv = torch.nn.functional.conv1d(g[None, None], kernel[None, None], padding="same")[0, 0]
        peak = peak * conv[len(x) // 2]
        var = (conv * x**2).sum() / conv.sum()
        assert abs(var - (s**2 + v)) < 1e-6
    assert abs(peak - alpha * coef) < 1e-6
    assert torch.allclose(torch.exp(2 * log_s[0]), scales**2 + v)


def test_smoothed_limits_and_gradients():
    gen = torch.Generator().manual_seed(0)
    log_s = (torch.randn(5, 3, generator=gen, dtype=torch.float64) - 2).requires_grad_()
    logits = torch.randn(5, 1, generator=gen, dtype=torch.float64).requires_grad_()
    t = torch.rand(5, generator=gen, dtype=torch.float64) * 0.1
    same = smoothed(log_s, logits, torch.zeros(5, dtype=torch.float64), 0.2)
    assert torch.allclose(same[0], log_s) and torch.allclose(same[1], logits)
    assert torch.autograd.gradcheck(lambda a, b: smoothed(a, b, t, 0.2), (log_s, logits))
    # far smaller than the interval: opacity falls as (s / sqrt(v))^3, scales become sqrt(v)
    tiny = smoothed(torch.full((1, 3), -20.0, dtype=torch.float64), torch.zeros(1), t[:1], 0.2)
    assert torch.allclose(torch.exp(tiny[0]), (0.2 * t[:1] ** 2).sqrt().expand(1, 3))
    assert torch.sigmoid(tiny[1]) < 1e-20


def test_model_with_filter_trains_renders_and_resumes_exactly():
    scene, data = synthetic_scene(size=24)
    cfg = config(filter_3d=0.2, densify_start=5, densify_interval=10)
    model, resumed, _ = straight_and_resumed(cfg, scene, data, saved_at=25, steps=40)
    assert len(model.filter_intervals) == model.num_gaussians
    assert torch.equal(model.filter_intervals, resumed.filter_intervals)
    expected = sampling_intervals(model.params["means"].detach(), data.cameras)
    assert torch.allclose(model.filter_intervals, expected, rtol=0, atol=0.05 * expected.max())
    g = model.gaussians()
    assert (g["log_scales"] > model.params["log_scales"]).all()  # every scale grew
    assert (g["opacity_logits"] < model.params["opacity_logits"]).all()  # every opacity fell
    splats = model.splats()  # what export writes: the filter baked in
    assert torch.allclose(torch.from_numpy(splats["log_scales"]), g["log_scales"].detach())
    out = model.render(data.cameras[0])
    assert torch.isfinite(out["rgb"]).all()
    off = GaussianModel(config(densify_start=5, densify_interval=10), scene)
    train_step(off, data, 0)
    assert len(off.filter_intervals) == 0
    assert torch.equal(off.gaussians()["log_scales"], off.params["log_scales"])
