"""Positional encoding: the output dimensions and layout of Mildenhall et al. 2020 (eq. 4)."""

import math

import torch

from recon.fields.encodings import positional_encoding, positional_encoding_dim


def test_positional_encoding_dimensions():
    x = torch.rand(5, 3) * 2 - 1
    assert positional_encoding(x, 10).shape == (5, 63)
    assert positional_encoding(x, 10, include_input=False).shape == (5, 60)
    assert positional_encoding(x, 4).shape == (5, 27)
    assert positional_encoding_dim(3, 10) == 63 and positional_encoding_dim(3, 4, False) == 24


def test_layout_matches_seed_reference_written_out():
    x = torch.tensor([[0.3, -0.7, 0.11]], dtype=torch.float64)
    L = 3
    expected = [0.3, -0.7, 0.11]
    for d in range(3):  # per coordinate: its L sines, then its L cosines
        expected += [math.sin(2**j * math.pi * x[0, d].item()) for j in range(L)]
        expected += [math.cos(2**j * math.pi * x[0, d].item()) for j in range(L)]
    torch.testing.assert_close(
        positional_encoding(x, L)[0], torch.tensor(expected, dtype=torch.float64)
    )


def test_highest_band_wavelength_problem2():
    # the band j = 9 has period 2 / 2^9 = 0.00390625 in normalized units
    x = torch.tensor([[0.1, 0.0, 0.0], [0.1 + 2 / 512, 0.0, 0.0]], dtype=torch.float64)
    enc = positional_encoding(x, 10, include_input=False)
    sin9 = enc[:, 9]  # coordinate 0, band 9 sine
    assert abs(sin9[0] - sin9[1]) < 1e-9


def test_leading_batch_dims_and_gradient():
    x = torch.rand(2, 4, 3, requires_grad=True)
    out = positional_encoding(x, 2)
    assert out.shape == (2, 4, 15)
    out.sum().backward()
    assert torch.isfinite(x.grad).all()
