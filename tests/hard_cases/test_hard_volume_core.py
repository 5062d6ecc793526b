"""Volume-core hard cases not already in tests/volrend/test_volrend.py (opaque one-hot, sigma = 0,
float64 gradcheck are there): 4,096+ samples without transmittance underflow to NaN,
zero-length and enormous intervals, rays that miss the box or start inside it."""

import math

import torch

from recon.volrend import ray_aabb_intersect, render_weights, volume_render


def finite_grads(out, *inputs):
    grads = torch.autograd.grad(out, inputs, allow_unused=True)
    return all(g is None or torch.isfinite(g).all() for g in grads)


def test_8192_samples_padded_and_packed_keep_transmittance_finite_and_exact():
    S = 8192
    sig = torch.full((1, S), 2.0, dtype=torch.float32, requires_grad=True)
    t = torch.linspace(0, 8, S + 1)
    w, trans, _ = render_weights(sig, t[:-1][None], t[1:][None])
    # T_i = exp(-2 t_i) exactly; it underflows to 0 (never NaN) far along the ray.
    torch.testing.assert_close(trans[0], torch.exp(-2 * t[:-1]), rtol=1e-4, atol=1e-30)
    assert torch.isfinite(w).all() and abs(float(w.detach().sum()) - (1 - math.exp(-16.0))) < 1e-5
    assert finite_grads(w.sum() + trans.sum(), sig)
    wp, _, _ = render_weights(sig[0], t[:-1], t[1:], torch.zeros(S, dtype=torch.long))
    torch.testing.assert_close(wp, w[0], rtol=1e-4, atol=1e-9)


def test_8192_opaque_samples_underflow_to_zero_not_nan():
    S = 8192
    sig = torch.full((1, S), 1e4, dtype=torch.float64, requires_grad=True)
    t = torch.linspace(0, 1000, S + 1, dtype=torch.float64)
    r = volume_render(
        sig,
        torch.rand(1, S, 3, dtype=torch.float64),
        t[:-1][None],
        t[1:][None],
        background=torch.ones(3, dtype=torch.float64),
    )
    # the optical depth per sample is capped at 50 inside the sum: T_2 = e^-50, then smaller
    assert finite_grads(r.rgb.sum() + r.depth.sum(), sig)
    w, trans = r.weights.detach(), r.transmittance.detach()
    assert float(w[0, 0]) == 1.0 and float(w[0, 1:].sum()) < 1e-21
    assert float(trans[0, 1:].max()) <= 2e-22 and torch.isfinite(trans).all()


def test_zero_length_intervals_contribute_nothing():
    sig = torch.tensor([[5.0, 1e6, 5.0]], dtype=torch.float64, requires_grad=True)
    t0 = torch.tensor([[0.0, 1.0, 1.0]], dtype=torch.float64)
    t1 = torch.tensor([[1.0, 1.0, 2.0]], dtype=torch.float64)  # the middle one has length 0
    w, trans, alpha = render_weights(sig, t0, t1)
    assert finite_grads(w.sum(), sig)
    w, trans, alpha = w.detach(), trans.detach(), alpha.detach()
    assert float(alpha[0, 1]) == 0.0 and float(w[0, 1]) == 0.0
    torch.testing.assert_close(trans[0, 2], trans[0, 1])


def test_enormous_intervals_saturate_without_inf_or_nan():
    for dtype in (torch.float32, torch.float64):
        big = torch.finfo(dtype).max / 4
        sig = torch.tensor([[1e-3, 1e30, 1.0]], dtype=dtype, requires_grad=True)
        t0 = torch.tensor([[0.0, 1.0, 2.0]], dtype=dtype)
        t1 = torch.tensor([[1.0, big, 3.0]], dtype=dtype)  # sigma delta overflows to inf
        w, trans, alpha = render_weights(sig, t0, t1)
        assert finite_grads(w.sum(), sig)
        w, trans, alpha = w.detach(), trans.detach(), alpha.detach()
        assert torch.isfinite(w).all() and torch.isfinite(trans).all()
        assert float(alpha[0, 1]) == 1.0 and float(w[0, 2]) < 2e-22  # T capped at e^-50
        torch.testing.assert_close(w.sum(), torch.tensor(1.0, dtype=dtype))


def test_rays_that_miss_the_box_or_start_inside_it():
    aabb = torch.tensor([[-1.0, -1, -1], [1, 1, 1]])
    o = torch.tensor([[0.0, 0, -5], [0, 3, -5], [0.2, 0.1, 0.0], [0, 0, 5], [5, 5, 5], [1, 1, -5]])
    d = torch.tensor([[0.0, 0, 1], [0, 0, 1], [1, 0, 0], [0, 0, 1], [0, 0, -1], [0, 0, 1]])
    near, far, hit = ray_aabb_intersect(o, d, aabb)
    assert hit.tolist() == [True, False, True, False, False, False]  # last: grazes an edge only
    torch.testing.assert_close(
        torch.stack([near[:3], far[:3]]), torch.tensor([[4.0, 0, 0], [6, 0, 0.8]])
    )
    assert torch.isfinite(near).all() and torch.isfinite(far).all()
    # a missed ray has zero-length intervals: background colour, zero opacity, no NaN
    s = torch.linspace(0, 1, 65)
    t0, t1 = (
        near[:, None] + (far - near)[:, None] * s[:-1],
        near[:, None] + (far - near)[:, None] * s[1:],
    )
    r = volume_render(
        torch.full(t0.shape, 50.0),
        torch.rand(*t0.shape, 3),
        t0,
        t1,
        background=torch.tensor([0.2, 0.4, 0.6]),
    )
    torch.testing.assert_close(r.rgb[~hit], torch.tensor([0.2, 0.4, 0.6]).expand(4, 3))
    assert r.acc[~hit].abs().max() == 0 and r.acc[hit].min() > 0.99
