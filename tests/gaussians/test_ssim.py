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


def test_the_torch_path_matches_the_numba_one_and_gradcheck(monkeypatch):
    """The torch algebra a GPU runs (`devices.uses_cpu_kernels` off) against the numba pair in
    float64: value and gradient to round-off, and its hand-derived backward against finite
    differences (torch.autograd.gradcheck)."""
    from recon import devices

    gen = torch.Generator().manual_seed(2)
    y = torch.rand(3, 23, 31, generator=gen, dtype=torch.float64)
    x = (y + 0.3 * torch.randn(3, 23, 31, generator=gen, dtype=torch.float64)).clamp(0, 1)
    x1 = x.clone().requires_grad_()
    ours = ssim(x1, y)
    (g_numba,) = torch.autograd.grad(ours, x1)
    monkeypatch.setattr(devices, "uses_cpu_kernels", lambda t: False)
    x2 = x.clone().requires_grad_()
    theirs = ssim(x2, y)
    (g_torch,) = torch.autograd.grad(theirs, x2)
    torch.testing.assert_close(theirs, ours, rtol=1e-13, atol=1e-14)
    torch.testing.assert_close(g_torch, g_numba, rtol=1e-10, atol=1e-15)
    small = x[:, :14, :13].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda t: ssim(t, y[:, :14, :13]), (small,))
    assert abs(ssim(y.clone(), y).item() - 1.0) < 1e-12


def test_the_torch_blurs_are_the_numba_ones_and_adjoint():
    from recon.gaussians.ssim import blur_transpose, blur_valid

    rng = np.random.default_rng(3)
    x, g = rng.random((4, 20, 17)), rng.random((4, 10, 7))
    taps = gaussian_taps()
    torch.testing.assert_close(blur_valid(torch.from_numpy(x)).numpy(), _blur_valid(x, taps))
    torch.testing.assert_close(
        blur_transpose(torch.from_numpy(g)).numpy(), _blur_transpose(g, taps)
    )
