"""The compositing quadrature: a worked example, padded == packed, limiting cases, stability."""

import math

import pytest
import torch

from recon.volrend import (
    accumulate_along_rays,
    alpha_compositing,
    exclusive_cumsum,
    render_weights,
    render_with_fn,
    surface_depth,
    volume_render,
)


def worked_example():
    sigma = torch.tensor([[0.1, 2.0, 5.0, 1.0]], dtype=torch.float64)
    color = torch.tensor([[0.2, 0.8, 0.5, 0.9]], dtype=torch.float64)[..., None].repeat(1, 1, 3)
    starts = torch.arange(4, dtype=torch.float64)[None] * 0.5
    return sigma, color, starts, starts + 0.5


def test_volume_render_worked_numbers():
    sigma, color, t0, t1 = worked_example()
    out = volume_render(sigma, color, t0, t1)
    assert out.rgb[0, 0].item() == pytest.approx(0.661566, abs=1e-6)
    assert out.acc[0].item() == pytest.approx(0.982578, abs=1e-6)
    assert out.depth[0].item() == pytest.approx(0.884, abs=1e-3)
    expected_w = [0.048771, 0.601292, 0.321213, 0.011302]
    assert out.weights[0].tolist() == pytest.approx(expected_w, abs=1e-6)
    expected_T = [1.0, 0.951229, 0.349938, 0.028725]
    assert out.transmittance[0].tolist() == pytest.approx(expected_T, abs=1e-6)


def test_volume_render_float32_and_background():
    sigma, color, t0, t1 = (x.float() for x in worked_example())
    bg = torch.tensor([0.0, 1.0, 0.5])
    out = volume_render(sigma, color, t0, t1, background=bg)
    residual = 1 - 0.982578
    assert out.rgb[0, 0].item() == pytest.approx(0.661566, abs=2e-6)
    assert out.rgb[0, 1].item() == pytest.approx(0.661566 + residual, abs=2e-6)
    assert out.rgb[0, 2].item() == pytest.approx(0.661566 + 0.5 * residual, abs=2e-6)


def test_exclusive_cumsum_packed_example():
    x = torch.tensor([1.0, 2.0, 3.0, 4.0])
    ri = torch.tensor([0, 0, 1, 1])
    assert exclusive_cumsum(x, ri).tolist() == [0.0, 1.0, 0.0, 3.0]


def random_packed(R=7, max_s=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, max_s, (R,), generator=g)
    counts[2] = 0  # a ray with no samples
    S = int(counts.max())
    sig = torch.rand(R, S, generator=g, dtype=torch.float64) * 5
    deltas = torch.rand(R, S, generator=g, dtype=torch.float64) * 0.2
    t1 = torch.cumsum(deltas, dim=-1) + 1.0
    t0 = t1 - deltas
    rgb = torch.rand(R, S, 3, generator=g, dtype=torch.float64)
    mask = torch.arange(S)[None] < counts[:, None]
    return sig, rgb, t0, t1, mask


def test_padded_equals_packed_values_and_gradients():
    sig, rgb, t0, t1, mask = random_packed()
    R = sig.shape[0]
    sig_p = sig.clone().requires_grad_()
    sig_k = sig.clone().requires_grad_()
    bg = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64)
    # padded: masked samples get zero density, which contributes nothing
    pad = volume_render(sig_p * mask, rgb, t0, t1, background=bg)
    ri = torch.arange(R)[:, None].expand_as(mask)[mask]
    pk = volume_render(sig_k[mask], rgb[mask], t0[mask], t1[mask], ri, R, background=bg)
    for a, b in [(pad.rgb, pk.rgb), (pad.acc, pk.acc), (pad.depth, pk.depth)]:
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(pad.weights[mask], pk.weights, rtol=1e-10, atol=1e-12)
    w = torch.rand(R, 3, dtype=torch.float64)
    (pad.rgb * w).sum().add(pad.depth.sum()).backward()
    (pk.rgb * w).sum().add(pk.depth.sum()).backward()
    torch.testing.assert_close(sig_p.grad * mask, sig_k.grad * mask, rtol=1e-9, atol=1e-12)


def test_packed_precision_after_many_opaque_rays():
    # 2000 opaque rays precede a ray of tiny optical depth: the global float64 running sum
    # must not swamp the last ray's own transmittance.
    n_before = 2000
    sig = torch.cat([torch.full((n_before * 8,), 1e6), torch.full((8,), 1e-6)])
    t0 = torch.arange(sig.shape[0], dtype=torch.float32) % 8
    ri = torch.arange(n_before + 1).repeat_interleave(8)
    _, trans, _ = render_weights(sig, t0, t0 + 1.0, ri)
    expected = torch.exp(-torch.arange(8) * 1e-6)
    torch.testing.assert_close(trans[-8:], expected, rtol=0, atol=1e-9)


def test_opaque_sample_gives_one_hot_weights():
    sig = torch.tensor([[0.0, 0.0, 1e4, 3.0, 1e4]])
    t0 = torch.arange(5.0)[None]
    out = volume_render(sig, torch.rand(1, 5, 3), t0, t0 + 1.0)
    torch.testing.assert_close(out.weights, torch.tensor([[0.0, 0.0, 1.0, 0.0, 0.0]]))
    assert out.acc.item() == 1.0


def test_zero_density_everywhere():
    sig = torch.zeros(3, 16, requires_grad=True)
    t0 = torch.linspace(0, 1, 16).expand(3, 16)
    bg = torch.tensor([0.1, 0.5, 0.9])
    out = volume_render(sig, torch.rand(3, 16, 3), t0, t0 + 1 / 16, background=bg)
    assert (out.acc == 0).all() and (out.weights == 0).all()
    torch.testing.assert_close(out.rgb, bg.expand(3, 3))
    out.rgb.sum().backward()
    assert torch.isfinite(sig.grad).all() and sig.grad.abs().sum() > 0


@pytest.mark.parametrize("tau", [1e-8, 1e-4, 1e-1, 1.0, 10.0, 1e2, 1e4])
def test_weights_plus_residual_is_one_and_gradients_finite(tau):
    S = 4096
    sig = torch.full((2, S), tau, requires_grad=True)
    t0 = torch.arange(S, dtype=torch.float32).expand(2, S)
    out = volume_render(sig, torch.rand(2, S, 3), t0, t0 + 1.0)
    residual = torch.exp(-(sig * 1.0).double().sum(-1))
    torch.testing.assert_close(
        out.acc.double() + residual, torch.ones(2, dtype=torch.float64), atol=1e-5, rtol=0
    )
    (out.rgb.sum() + out.depth.sum()).backward()
    assert torch.isfinite(sig.grad).all()
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.weights).all()


def test_alpha_keeps_tiny_optical_depth():
    # 1 - exp(-1e-8) is 0 in float32; expm1 keeps it, so gradients reach empty space
    _, _, alphas = render_weights(torch.tensor([1e-8]), torch.tensor([0.0]), torch.tensor([1.0]))
    assert alphas.item() == pytest.approx(1e-8, rel=1e-4)


def test_gradcheck_float64_padded_and_packed():
    sig, rgb, t0, t1, mask = random_packed(R=3, max_s=6, seed=1)
    sig = sig.clone().requires_grad_()
    rgb = rgb.clone().requires_grad_()
    ri = torch.arange(3)[:, None].expand_as(mask)[mask]

    def padded(s, c):
        out = volume_render(
            s, c, t0, t1, background=torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
        )
        return out.rgb, out.depth

    def packed(s, c):
        out = volume_render(s, c, t0[mask], t1[mask], ri, 3)
        return out.rgb, out.acc

    assert torch.autograd.gradcheck(padded, (sig, rgb))
    assert torch.autograd.gradcheck(
        packed, (sig[mask].detach().requires_grad_(), rgb[mask].detach().requires_grad_())
    )


def test_accumulate_packed_needs_n_rays_and_handles_empty_rays():
    w = torch.tensor([0.5, 0.5])
    ri = torch.tensor([2, 2])
    assert accumulate_along_rays(w, None, ri, 4)[:, 0].tolist() == [0.0, 0.0, 1.0, 0.0]
    with pytest.raises(ValueError):
        accumulate_along_rays(w, None, ri)


def test_render_with_fn_matches_tensors():
    sigma, color, t0, t1 = worked_example()
    calls = []

    def fn(ts, te, ri):
        calls.append(ri)
        return color, sigma

    out = render_with_fn(fn, t0, t1)
    assert calls == [None]
    assert out.rgb[0, 0].item() == pytest.approx(0.661566, abs=1e-6)


def test_continuous_limit_matches_beer_lambert():
    # constant density sigma on [0, L]: acc -> 1 - exp(-sigma L), depth -> closed form
    sigma, L, S = 1.3, 2.0, 20000
    t = torch.linspace(0, L, S + 1, dtype=torch.float64)
    out = volume_render(
        torch.full((1, S), sigma, dtype=torch.float64),
        torch.ones(1, S, 3, dtype=torch.float64),
        t[None, :-1],
        t[None, 1:],
    )
    assert out.acc.item() == pytest.approx(1 - math.exp(-sigma * L), rel=1e-9)
    exact_depth = (1 - math.exp(-sigma * L) * (1 + sigma * L)) / sigma  # int t sigma e^{-sigma t}
    assert out.depth.item() == pytest.approx(exact_depth, rel=1e-6)


def test_alpha_compositing_example_and_termination():
    alpha = torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64)
    w, used = alpha_compositing(alpha)
    torch.testing.assert_close(w, torch.tensor([0.5, 0.25, 0.125], dtype=torch.float64))
    w, used = alpha_compositing(alpha, t_min=0.2)  # T (1 - alpha) at the third: 0.125 < 0.2
    torch.testing.assert_close(w, torch.tensor([0.5, 0.25, 0.0], dtype=torch.float64))
    assert used.tolist() == [0.5, 0.5, 0.0]


def test_alpha_compositing_is_render_weights_with_alpha_given():
    g = torch.Generator().manual_seed(4)
    sigmas = torch.rand(6, 9, generator=g, dtype=torch.float64) * 4
    t = torch.sort(torch.rand(6, 10, generator=g, dtype=torch.float64), dim=-1).values
    w_sigma, _, alphas = render_weights(sigmas, t[:, :-1], t[:, 1:])
    w_alpha, _ = alpha_compositing(alphas)
    torch.testing.assert_close(w_alpha, w_sigma, rtol=1e-12, atol=1e-14)


def test_alpha_compositing_matches_the_cumprod_definition_padded_and_packed():
    """Brute-force twin: T_i as a running product of (1 - alpha_j), and the 3DGS stop rule
    applied literally; packed (rows of a ray along dim 0, trailing pixels) equals padded."""
    g = torch.Generator().manual_seed(5)
    alpha = torch.rand(8, 30, generator=g, dtype=torch.float64) * 0.99
    alpha = alpha * (torch.rand(8, 30, generator=g, dtype=torch.float64) < 0.6)
    t_min = 1e-3
    expected = torch.zeros_like(alpha)
    for r in range(8):
        T = 1.0
        for i in range(30):
            a = float(alpha[r, i])
            if a > 0 and T * (1 - a) < t_min:
                break
            expected[r, i] = T * a
            T *= 1 - a
    padded, _ = alpha_compositing(alpha, t_min=t_min)
    torch.testing.assert_close(padded, expected, rtol=1e-12, atol=1e-14)
    rays = torch.arange(2).repeat_interleave(15)  # two rays of 15 samples, 8 pixels each
    packed, _ = alpha_compositing(alpha.T.contiguous(), rays, t_min=t_min)
    split = torch.cat(
        [
            alpha_compositing(alpha[:, :15], t_min=t_min)[0],
            alpha_compositing(alpha[:, 15:], t_min=t_min)[0],
        ],
        dim=1,
    )
    torch.testing.assert_close(packed.T, split, rtol=1e-12, atol=1e-14)


def test_surface_depth_divides_by_opacity_and_is_zero_where_nothing_is_hit():
    expected = torch.tensor([1.5, 0.0, 2.0])
    acc = torch.tensor([0.5, 0.0, 1.0])
    torch.testing.assert_close(surface_depth(expected, acc), torch.tensor([3.0, 0.0, 2.0]))
