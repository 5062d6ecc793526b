"""Renders area-downsampled to a coarser output: rgb and acc averaged, depth acc-weighted."""

import numpy as np
import pytest
import torch

from recon.render.views import area_downsample_render


def test_worked_example_two_by_two_block():
    out = {
        "rgb": torch.tensor([[[1.0, 0, 0], [0, 1.0, 0]], [[0, 0, 1.0], [1.0, 1.0, 1.0]]]),
        "depth": torch.tensor([[2.0, 4.0], [7.0, 9.0]]),
        "acc": torch.tensor([[1.0, 1.0], [0.0, 0.0]]),
    }
    small = area_downsample_render(out, 1, 1)
    assert small["acc"].item() == pytest.approx(0.5)
    assert small["depth"].item() == pytest.approx(3.0)  # the uncovered pixels' depths do not count
    assert small["rgb"][0, 0].tolist() == pytest.approx([0.5, 0.5, 0.5])


def test_same_size_is_untouched_and_empty_pixels_have_depth_zero():
    out = {"rgb": torch.rand(4, 6, 3), "depth": torch.rand(4, 6), "acc": torch.zeros(4, 6)}
    assert area_downsample_render(out, 6, 4) is out
    small = area_downsample_render(out, 3, 2)
    assert small["rgb"].shape == (2, 3, 3) and torch.all(small["depth"] == 0)
    assert np.allclose(
        small["rgb"].numpy(), out["rgb"].reshape(2, 2, 3, 2, 3).mean((1, 3)).numpy(), atol=1e-6
    )
