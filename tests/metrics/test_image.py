import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from recon.metrics.image import depth_errors, psnr, ssim


def _image(seed: int, h: int = 32, w: int = 40) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(h, w, 3, generator=g, dtype=torch.float64)


def test_psnr_identical_is_inf():
    x = _image(0)
    assert psnr(x, x).item() == math.inf


@pytest.mark.parametrize("e", [0.1, 0.01, 0.25])
def test_psnr_constant_offset_closed_form(e):
    # MSE = e^2 exactly, so PSNR = 10 log10(1 / e^2) = -20 log10(e).
    x = _image(1) * 0.5
    assert psnr(x + e, x).item() == pytest.approx(-20 * math.log10(e), abs=1e-9)
    # max_val = 255 with the same relative offset gives the same number.
    assert psnr(255 * (x + e), 255 * x, max_val=255.0).item() == pytest.approx(
        -20 * math.log10(e), abs=1e-9
    )


def test_psnr_batched_and_numpy_input():
    x = torch.stack([_image(2), _image(3)])
    y = x.clone()
    y[0] += 0.1
    y[1] += 0.01
    out = psnr(y.numpy(), x.numpy())
    assert out.shape == (2,)
    assert out.tolist() == pytest.approx([20.0, 40.0], abs=1e-9)


def test_ssim_identical_is_one():
    x = _image(4)
    assert ssim(x, x).item() == pytest.approx(1.0, abs=1e-12)


def test_ssim_matches_skimage_gaussian_settings():
    # Independent twin: skimage with the Gaussian window of Wang et al. (sigma 1.5,
    # truncate 3.5 -> 11 taps) and population covariances.
    x = _image(5)
    y = (x + 0.1 * torch.randn(x.shape, generator=torch.Generator().manual_seed(6))).clamp(0, 1)
    expected = structural_similarity(
        x.numpy(),
        y.numpy(),
        data_range=1.0,
        channel_axis=-1,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
    )
    assert ssim(y, x).item() == pytest.approx(expected, abs=1e-6)


def test_ssim_batched_decreases_with_noise():
    x = _image(7, 48, 48)
    noise = torch.randn(x.shape, generator=torch.Generator().manual_seed(8), dtype=x.dtype)
    ys = torch.stack([(x + s * noise).clamp(0, 1) for s in (0.01, 0.05, 0.2)])
    values = ssim(ys, x.expand_as(ys))
    assert values.shape == (3,)
    assert values[0] > values[1] > values[2]


def test_ssim_rejects_small_images():
    with pytest.raises(ValueError):
        ssim(torch.zeros(8, 8, 3), torch.zeros(8, 8, 3))


def test_depth_errors_hand_example():
    gt = np.array([[1.0, 2.0], [4.0, 0.0]])  # the 0 is "no ground truth"
    pred = np.array([[1.1, 2.0], [6.0, 5.0]])
    out = depth_errors(pred, gt)
    # valid pixels: (1.1 vs 1), (2 vs 2), (6 vs 4)
    assert out["count"] == 3
    assert out["abs_rel"] == pytest.approx((0.1 + 0.0 + 0.5) / 3)
    assert out["rmse"] == pytest.approx(math.sqrt((0.01 + 0.0 + 4.0) / 3))
    assert out["delta_1.25"] == pytest.approx(2 / 3)  # ratios 1.1, 1.0, 1.5


def test_depth_errors_mask_and_empty():
    gt = np.array([[1.0, 2.0]])
    pred = np.array([[1.5, 2.0]])
    out = depth_errors(pred, gt, mask=np.array([[False, True]]))
    assert out["count"] == 1 and out["abs_rel"] == 0.0 and out["delta_1.25"] == 1.0
    empty = depth_errors(pred, gt, mask=np.zeros((1, 2), bool))
    assert empty["count"] == 0 and math.isnan(empty["rmse"])


def test_masked_psnr_with_a_full_mask_is_psnr():
    from recon.metrics.image import psnr_masked

    a, b = _image(1), _image(2)
    assert psnr_masked(a, b, torch.ones(32, 40, dtype=torch.bool)).item() == pytest.approx(
        psnr(a, b).item()
    )


def test_masked_psnr_counts_only_the_mask():
    from recon.metrics.image import psnr_masked

    a = torch.zeros(4, 4, 3, dtype=torch.float64)
    b = a.clone()
    b[0] = 0.1  # an error of 0.1 in the top row only
    mask = torch.zeros(4, 4, dtype=torch.bool)
    mask[0] = True
    assert psnr_masked(a, b, mask).item() == pytest.approx(20.0)  # -20 log10(0.1)
    assert psnr_masked(a, b, ~mask).item() == math.inf


def test_border_mask_worked_example():
    from recon.metrics.image import border_mask

    m = border_mask(20, 10, 0.15)
    rows = [r for r in range(20) if m[r, 5]]
    cols = [c for c in range(10) if m[10, c]]
    assert rows == [0, 1, 2, 17, 18, 19] and cols == [0, 1, 8, 9]
    assert m.sum().item() == 20 * 10 - 14 * 6
