"""SDF pieces: VolSDF's density against its formula and its limit (the surface depth, as NeuS
reaches too), the exact SDFs' eikonal residual, the geometric initialisation (a sphere), and
the field's gradient against central differences in float64."""

import math

import pytest
import torch

from recon.fields.sdf import (
    SDFField,
    box_sdf,
    eikonal_loss,
    sdf_and_gradient,
    sphere_sdf,
)
from recon.volrend.sdf_density import laplace_cdf, neus_alpha, volsdf_density
from recon.volrend.volrend import alpha_compositing

F64 = torch.float64


def test_laplace_cdf_worked_example_and_limits():
    s = torch.tensor([0.0, -0.1, 0.1, -50.0, 50.0], dtype=F64)
    out = laplace_cdf(s, 0.1)
    expected = [0.5, 0.5 / math.e, 1 - 0.5 / math.e, 0.5 * math.exp(-500), 1 - 0.5 * math.exp(-500)]
    torch.testing.assert_close(out, torch.tensor(expected, dtype=F64))
    assert torch.isfinite(laplace_cdf(torch.tensor([-1e6, 1e6]), 1e-3)).all()


def test_volsdf_density_is_one_over_beta_inside_and_vanishes_outside():
    beta = 0.05
    sdf = torch.tensor([-1.0, 0.0, 1.0], dtype=F64)
    sigma = volsdf_density(sdf, beta)
    assert sigma[0] == pytest.approx((1 - 0.5 * math.exp(-1 / beta)) / beta)
    assert sigma[1] == pytest.approx(0.5 / beta)
    assert sigma[2] == pytest.approx(0.5 * math.exp(-1 / beta) / beta)


def _plane_ray_depth(alphas: torch.Tensor, t_mid: torch.Tensor) -> float:
    w, _ = alpha_compositing(alphas)
    return float((w * t_mid).sum() / w.sum())


@pytest.mark.parametrize("sharp", [20.0, 200.0])
def test_volsdf_and_neus_put_a_ray_at_the_surface_as_they_sharpen(sharp):
    """A ray along +z through the plane z = 1 (sdf = 1 - t): the expected depth approaches 1
    for both conversions, VolSDF with beta = 1 / sharp, NeuS with s = sharp."""
    t = torch.linspace(0.0, 2.0, 4001, dtype=F64)
    t0, t1 = t[:-1], t[1:]
    mid = 0.5 * (t0 + t1)
    sigma = volsdf_density(1.0 - mid, 1.0 / sharp)
    volsdf = _plane_ray_depth(-torch.expm1(-sigma * (t1 - t0)), mid)
    neus = _plane_ray_depth(neus_alpha(1.0 - t0, 1.0 - t1, sharp), mid)
    tol = 3.0 / sharp
    assert abs(volsdf - 1.0) < tol and abs(neus - 1.0) < tol


def test_exact_sdfs_have_unit_gradients():
    gen = torch.Generator().manual_seed(0)
    x = (torch.rand(500, 3, generator=gen, dtype=F64) * 2 - 1).requires_grad_(True)
    for f in (
        lambda p: sphere_sdf(p, 0.5),
        lambda p: box_sdf(p, torch.tensor([0.3, 0.5, 0.2], dtype=F64)),
    ):
        (g,) = torch.autograd.grad(f(x).sum(), x)
        assert eikonal_loss(g) < 1e-20
    assert box_sdf(
        torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=F64),
        torch.tensor([0.3, 0.5, 0.2], dtype=F64),
    ).tolist() == pytest.approx([-0.2, 0.7])


def test_initial_field_is_the_sphere_with_unit_gradient():
    torch.manual_seed(0)
    field = SDFField(n_levels=4, log2_table_size=10, n_max=64, width=64, radius=0.5)
    gen = torch.Generator().manual_seed(1)
    d = torch.nn.functional.normalize(torch.randn(256, 3, generator=gen), dim=-1)
    r = torch.rand(256, 1, generator=gen) * 1.5 + 0.05
    sdf, grad, _ = sdf_and_gradient(field, r * d, create_graph=False)
    torch.testing.assert_close(sdf.detach(), r[:, 0] - 0.5, rtol=0, atol=1e-5)
    torch.testing.assert_close(grad, d, rtol=0, atol=1e-4)  # the outward unit normal
    assert float(eikonal_loss(grad)) < 1e-8


@pytest.mark.parametrize("active_levels", [3, 1])
def test_field_gradient_matches_central_differences_float64(active_levels):
    torch.manual_seed(0)
    field = SDFField(n_levels=3, log2_table_size=8, n_max=32, width=16).double()
    field.active_levels = active_levels  # coarse-to-fine: the finer levels read as zero
    with torch.no_grad():
        field.grid.table.normal_(0.0, 0.05)  # switched-on features so the grid matters
        field.layers[0].weight.normal_(0.0, 0.2)
    gen = torch.Generator().manual_seed(2)
    x = torch.rand(20, 3, generator=gen, dtype=F64) * 1.6 - 0.8
    _, grad, _ = sdf_and_gradient(field, x, create_graph=False)
    h = 1e-6
    for k in range(3):
        e = torch.zeros(3, dtype=F64)
        e[k] = h
        with torch.no_grad():
            fd = (field.sdf(x + e) - field.sdf(x - e)) / (2 * h)
        torch.testing.assert_close(grad[:, k], fd, rtol=1e-5, atol=1e-6)


def test_eikonal_loss_has_gradients_through_the_normal():
    torch.manual_seed(0)
    field = SDFField(n_levels=2, log2_table_size=8, n_max=32, width=16)
    with torch.no_grad():  # a residual away from the initial sphere, whose eikonal term is 0
        field.layers[-1].weight[0].normal_(0.0, 0.3)
    x = torch.rand(64, 3) * 2 - 1
    _, grad, _ = sdf_and_gradient(field, x, create_graph=True)
    eikonal_loss(grad).backward()
    assert field.layers[0].weight.grad is not None and field.layers[0].weight.grad.abs().sum() > 0


def test_eikonal_gradients_match_double_backward_through_the_torch_encoding_float64():
    """The chain-rule gradient and its parameter gradients (an eikonal loss, the numba
    Jacobian's table backward) against plain autograd in x through `hash_encode_torch`."""
    torch.manual_seed(0)
    field = SDFField(n_levels=3, log2_table_size=8, n_max=32, width=16).double()
    with torch.no_grad():
        field.grid.table.normal_(0.0, 0.05)
        field.layers[0].weight.normal_(0.0, 0.2)
    x = torch.rand(50, 3, generator=torch.Generator().manual_seed(3), dtype=F64) * 1.6 - 0.8

    def loss_and_grads(gradient):
        field.zero_grad()
        sdf, grad, feature = gradient(x)
        loss = eikonal_loss(grad) + sdf.square().mean() + feature.square().mean()
        loss.backward()
        return grad.detach(), {n: p.grad.clone() for n, p in field.named_parameters()}

    def by_autograd(points):
        points = points.clone().requires_grad_(True)  # x needs grad: the torch encoding
        sdf, feature = field(points)
        (grad,) = torch.autograd.grad(sdf.sum(), points, create_graph=True)
        return sdf, grad, feature

    grad, params = loss_and_grads(lambda p: sdf_and_gradient(field, p, create_graph=True))
    twin_grad, twin_params = loss_and_grads(by_autograd)
    torch.testing.assert_close(grad, twin_grad, rtol=1e-10, atol=1e-12)
    for name in params:
        torch.testing.assert_close(params[name], twin_params[name], rtol=1e-8, atol=1e-12)


def test_inactive_levels_change_nothing_and_get_no_gradient():
    torch.manual_seed(0)
    field = SDFField(n_levels=3, log2_table_size=8, n_max=32, width=16).double()
    with torch.no_grad():
        field.grid.table.normal_(0.0, 0.05)
        field.layers[0].weight.normal_(0.0, 0.2)
    x = torch.rand(50, 3, generator=torch.Generator().manual_seed(1), dtype=F64) * 2 - 1
    field.active_levels = 1
    sdf, grad, _ = sdf_and_gradient(field, x, create_graph=True)
    (sdf.sum() + eikonal_loss(grad)).backward()
    w_fine = field.layers[0].weight.grad[:, 3 + 2 :]  # the weights reading levels 1 and 2
    assert float(w_fine.abs().max()) == 0.0
    with torch.no_grad():  # the finer levels' features, whatever they hold, do not count
        before = field.sdf(x)
        field.layers[0].weight[:, 3 + 2 :].normal_(0.0, 1.0)
        torch.testing.assert_close(field.sdf(x), before)
