"""mip-NeRF 360 contraction: identity inside, continuity at |x| = 1, limit 2, finite gradients."""

import torch

from recon.volrend import contract, normalize_to_box, scene_to_unit_cube, unit_cube_to_scene
from recon.volrend.contraction import uncontract


def test_worked_values():
    x = torch.tensor([[0.3, -0.2, 0.5], [3.0, 0.0, 0.0], [0.0, -4.0, 0.0]])
    out = contract(x)
    torch.testing.assert_close(out[0], x[0])
    torch.testing.assert_close(out[1], torch.tensor([5 / 3, 0.0, 0.0]))
    torch.testing.assert_close(out[2], torch.tensor([0.0, -1.75, 0.0]))


def test_continuous_with_continuous_derivative_at_unit_sphere():
    d = torch.nn.functional.normalize(torch.randn(100, 3, dtype=torch.float64), dim=-1)
    e = 1e-7
    inner, outer = contract(d * (1 - e)), contract(d * (1 + e))
    assert (inner - outer).norm(dim=-1).max() < 3e-7
    # radial derivative 1 on both sides: d/dr (2 - 1/r) = 1/r^2 = 1 at r = 1
    h = 1e-4
    out_slope = (contract(d * (1 + 2 * h)) - contract(d * (1 + h))).norm(dim=-1) / h
    assert (out_slope - 1).abs().max() < 1e-3


def test_limit_two_at_infinity_and_monotone():
    r = torch.logspace(0, 30, 50, dtype=torch.float64)
    x = torch.stack([r, torch.zeros_like(r), torch.zeros_like(r)], -1)
    n = contract(x).norm(dim=-1)
    assert (n[1:] >= n[:-1]).all() and n.max() <= 2 and abs(n[-1] - 2) < 1e-12


def test_finite_gradients_from_zero_to_huge():
    x = torch.tensor(
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1e-20, 0, 0], [1e20, 1e20, 0], [5.0, 2.0, -1.0]],
        dtype=torch.float64,
        requires_grad=True,
    )
    contract(x).sum().backward()
    assert torch.isfinite(x.grad).all()
    xs = torch.randn(6, 3, dtype=torch.float64) * 3
    assert torch.autograd.gradcheck(contract, (xs.requires_grad_(),))


def test_scene_to_unit_cube():
    aabb = torch.tensor([[0.0, 0.0, 0.0], [2.0, 4.0, 2.0]])
    x = torch.tensor([[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [0.0, 0.0, 0.0]])
    torch.testing.assert_close(
        normalize_to_box(x, aabb), torch.tensor([[0.0, 0, 0], [1, 1, 1], [-1, -1, -1]])
    )
    torch.testing.assert_close(
        scene_to_unit_cube(x, aabb, False), torch.tensor([[0.5, 0.5, 0.5], [1, 1, 1], [0, 0, 0]])
    )
    far = torch.tensor([[1e9, 2.0, 1.0]])
    u = scene_to_unit_cube(torch.cat([x, far]), aabb, True)
    assert ((u >= 0) & (u <= 1)).all()
    torch.testing.assert_close(u[0], torch.tensor([0.5, 0.5, 0.5]))
    assert abs(u[3, 0].item() - 1.0) < 1e-6


def test_uncontract_and_unit_cube_to_scene_invert_the_forward_maps():
    torch.testing.assert_close(
        uncontract(torch.tensor([[5 / 3, 0.0, 0.0], [0.0, -1.75, 0.0]])),
        torch.tensor([[3.0, 0.0, 0.0], [0.0, -4.0, 0.0]]),
    )
    x = torch.randn(500, 3, dtype=torch.float64) * 3
    torch.testing.assert_close(uncontract(contract(x)), x)
    assert torch.isinf(uncontract(torch.tensor([[2.0, 0.0, 0.0], [0.0, 1.5, 1.5]]))).all()
    aabb = torch.tensor([[-1.0, -2.0, 0.0], [1.0, 2.0, 3.0]], dtype=torch.float64)
    for unbounded in (False, True):
        back = unit_cube_to_scene(scene_to_unit_cube(x, aabb, unbounded), aabb, unbounded)
        torch.testing.assert_close(back, x)
    # an unbounded cube's corner lies outside the contraction's ball: no point of the scene
    corner = unit_cube_to_scene(torch.ones(1, 3, dtype=torch.float64), aabb, True)
    assert torch.isinf(corner).all()
