"""The numba SSIM against pytorch_msssim (value and gradient, float64), and its blur adjoint."""

import numpy as np
import pytorch_msssim
import torch

from recon.gaussians.ssim import _blur_transpose, _blur_valid, gaussian_taps, ssim


def test_matches_pytorch_msssim_value_and_gradient():
    gen = torch.Generator().manual_seed(0)
    y = torch.rand(3, 37, 29, generator=gen, dtype=torch.float64)
    x = (y + 0.2 * torch.randn(3, 37, 29, generator=gen, dtype=torch.float64)).clamp(0, 1)
    x1, x2 = x.clone().requires_grad_(), x.clone().requires_grad_()
    ours = ssim(x1, y)
    ref = pytorch_msssim.ssim(x2[None], y[None], data_range=1.0, size_average=True)
    # pytorch_msssim builds its taps in float32: agreement is to ~1e-7, not 1e-15.
    assert torch.allclose(ours, ref, rtol=1e-6)
    (g1,) = torch.autograd.grad(ours, x1)
    (g2,) = torch.autograd.grad(ref, x2)
    assert torch.allclose(g1, g2, rtol=1e-5, atol=1e-9)


def test_identical_images_give_one():
    y = torch.rand(3, 16, 16, dtype=torch.float64)
    assert abs(ssim(y.clone(), y).item() - 1.0) < 1e-12


def test_blur_transpose_is_the_adjoint():
    """<blur(x), g> = <x, blur^T(g)> for random x, g."""
    rng = np.random.default_rng(1)
    taps = gaussian_taps()
    x = rng.random((2, 20, 17))
    g = rng.random((2, 10, 7))
    assert np.isclose((_blur_valid(x, taps) * g).sum(), (x * _blur_transpose(g, taps)).sum())
    assert np.isclose(gaussian_taps().sum(), 1.0)
