"""Compact tensors for model files: deflate round trip, int8 quantisation (worked example and
its error bound), vertex bitmasks."""

import torch

from recon.io.packed import (
    bits_indices,
    deflate,
    dequantize_int8,
    inflate,
    mask_bits,
    quantize_int8,
)


def test_deflate_round_trip_and_shrinks_redundant_data():
    x = torch.zeros(10_000, 3, dtype=torch.float16)
    x[::97] = 1.5
    blob = deflate(x)
    assert blob.dtype == torch.uint8 and blob.numel() < x.numel() * 2 / 10
    assert torch.equal(inflate(blob, torch.float16, (10_000, 3)), x)


def test_quantize_int8_worked_example_and_bound():
    q, scale = quantize_int8(torch.tensor([[0.5, 0.0], [-1.27, 0.0]]))
    assert torch.allclose(scale, torch.tensor([0.01, 1.0]))
    assert q[:, 0].tolist() == [50, -127] and q[:, 1].tolist() == [0, 0]
    x = torch.randn(5000, 27, generator=torch.Generator().manual_seed(0)) * torch.rand(27) * 4
    q, scale = quantize_int8(x)
    assert q.dtype == torch.int8 and int(q.abs().max()) == 127
    assert ((dequantize_int8(q, scale) - x).abs() <= scale / 2 + 1e-6).all()


def test_mask_bits_round_trip():
    idx = torch.tensor([0, 5, 8, 63, 64, 999])
    bits = mask_bits(idx, 1000)
    assert bits.shape == (125,) and bits.dtype == torch.uint8
    assert torch.equal(bits_indices(bits, 1000), idx)
