"""Reduced precision (bf16/fp16 inference where offered). nerf runs its MLP
matmuls in bf16 where the hardware has it (`precision`, tested against fp32 in test_nerf.py);
the other models train and render in float32. The shared math accepts half inputs: the
volume-rendering core and the torch hash encoding. Fed fp16/bf16 they must give the float32
image within the stated tolerance, never NaN/Inf - fp16 keeps ~3 decimal digits (tolerance
2e-3), bf16 ~2 (tolerance 1.5e-2)."""

import pytest
import torch

from recon.fields.hashgrid import hash_encode_torch, level_layout
from recon.volrend import volume_render

TOL = {torch.float16: 2e-3, torch.bfloat16: 1.5e-2}


def scene(R=512, S=96, seed=0):
    """Random rays through a density bump: transparent, semi-transparent and opaque rays."""
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(2.0, 6.0, S + 1).expand(R, -1)
    centre = 4.0 + 0.5 * torch.randn(R, 1, generator=g)
    peak = torch.logspace(-2, 2, R)[:, None]  # from almost empty to opaque
    mid = 0.5 * (t[:, 1:] + t[:, :-1])
    sigmas = peak * torch.exp(-(((mid - centre) / 0.3) ** 2))
    rgbs = torch.rand(R, S, 3, generator=g)
    return sigmas, rgbs, t[:, :-1].contiguous(), t[:, 1:].contiguous()


def max_error(low, ref) -> float:
    assert (
        low.rgb.dtype == low.acc.dtype
        and torch.isfinite(low.rgb).all()
        and torch.isfinite(low.acc).all()
    )
    return max(
        float((low.rgb.float() - ref.rgb).abs().max()),
        float((low.acc.float() - ref.acc).abs().max()),
    )


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_field_outputs_render_the_float32_image(dtype):
    """The inference case: a field evaluated in fp16/bf16, sample intervals kept in float32."""
    sig, rgb, t0, t1 = scene()
    bg = torch.ones(3)
    ref = volume_render(sig, rgb, t0, t1, background=bg)
    assert (
        max_error(volume_render(sig.to(dtype), rgb.to(dtype), t0, t1, background=bg), ref)
        < TOL[dtype]
    )


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_all_half_precision_rendering_adds_only_rounding_error(dtype):
    """Everything in fp16/bf16: compared with float32 rendering of the SAME rounded inputs (bf16
    cannot even hold t = 2..6 to better than 0.03, so the inputs themselves differ), the
    arithmetic in low precision stays within the stated tolerance."""
    sig, rgb, t0, t1 = (x.to(dtype) for x in scene())
    bg = torch.ones(3, dtype=dtype)
    ref = volume_render(sig.float(), rgb.float(), t0.float(), t1.float(), background=bg.float())
    low = volume_render(sig, rgb, t0, t1, background=bg)
    assert low.rgb.dtype == dtype and max_error(low, ref) < TOL[dtype]
    assert torch.isfinite(low.depth).all()
    assert float(((low.depth.float() - ref.depth) / 6).abs().max()) < TOL[dtype]


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_hash_encoding_with_a_half_precision_table_matches_float32(dtype):
    layout = level_layout(4, 8, 256, 2**12)
    g = torch.Generator().manual_seed(0)
    table = torch.randn(sum(layout["size"]), 2, generator=g)
    x = torch.rand(2000, 3, generator=g)
    ref = hash_encode_torch(x, table, layout)
    low = hash_encode_torch(x, table.to(dtype), layout)
    assert low.dtype == dtype and torch.isfinite(low).all()
    # features are O(1); the error is the table's rounding (the weights stay float32)
    assert float((low.float() - ref).abs().max()) < 4 * TOL[dtype]
