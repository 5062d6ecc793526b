"""The hash encoding's Jacobian in x: the numba kernel against the torch twin, both against
central differences of the encoding in float64, zero where the encoding clamps, and the
kernel's table gradient against autograd through the twin; the fused encoding + Jacobian
pass against the two twins, values and the table gradient of both outputs at once."""

import torch

from recon.fields.hashgrid import hash_encode_torch, level_layout
from recon.fields.hashgrid_jacobian import hash_encode_and_jacobian, hash_jacobian_torch

F64 = torch.float64
LAYOUT = level_layout(3, 4, 40, 2**9)  # a dense coarse level, hashed finer ones


def hash_jacobian(x, t, layout):
    """The numba kernel's Jacobian output alone."""
    return hash_encode_and_jacobian(x, t, layout)[1]


def table(seed=0):
    entries = sum(LAYOUT["size"])
    return torch.randn(entries, 2, generator=torch.Generator().manual_seed(seed), dtype=F64)


def points(n=64, seed=1):
    return torch.rand(n, 3, generator=torch.Generator().manual_seed(seed), dtype=F64) * 0.98 + 0.01


def test_jacobian_matches_central_differences_and_its_twin():
    t, x = table(), points()
    jac = hash_jacobian(x, t, LAYOUT)
    assert jac.shape == (64, 6, 3)
    torch.testing.assert_close(jac, hash_jacobian_torch(x, t, LAYOUT), rtol=1e-12, atol=1e-12)
    h = 1e-7
    for a in range(3):
        e = torch.zeros(3, dtype=F64)
        e[a] = h
        fd = (hash_encode_torch(x + e, t, LAYOUT) - hash_encode_torch(x - e, t, LAYOUT)) / (2 * h)
        torch.testing.assert_close(jac[..., a], fd, rtol=1e-5, atol=1e-5)


def test_worked_example_one_dense_level():
    """One level of resolution 2 (3^3 vertices, dense) holding f = 3 x + 5 y - 2 z at its
    vertices: trilinear interpolation reproduces the linear function, so J = (3, 5, -2)."""
    layout = level_layout(1, 2, 2, 2**9)
    ijk = torch.stack(torch.meshgrid(*[torch.arange(3)] * 3, indexing="ij"), -1).reshape(-1, 3)
    rows = ijk[:, 0] + 3 * ijk[:, 1] + 9 * ijk[:, 2]
    tab = torch.zeros(27, 1, dtype=F64)
    tab[rows, 0] = (ijk.to(F64) / 2) @ torch.tensor([3.0, 5.0, -2.0], dtype=F64)
    jac = hash_jacobian(points(10), tab, layout)
    torch.testing.assert_close(jac[:, 0], torch.tensor([[3.0, 5.0, -2.0]] * 10, dtype=F64))


def test_zero_outside_the_unit_cube():
    x = torch.tensor([[-0.1, 0.5, 0.5], [0.5, 1.2, 0.5], [0.3, 0.4, 0.5]], dtype=F64)
    jac = hash_jacobian(x, table(), LAYOUT)
    assert (jac[:2] == 0).all() and (jac[2] != 0).any()
    assert torch.equal(hash_jacobian_torch(x, table(), LAYOUT)[:2], jac[:2])


def test_table_gradient_matches_autograd_through_the_twin():
    t, x = table(), points()
    w = torch.randn(64, 6, 3, generator=torch.Generator().manual_seed(4), dtype=F64)
    t1 = t.clone().requires_grad_(True)
    (hash_jacobian(x, t1, LAYOUT) * w).sum().backward()
    t2 = t.clone().requires_grad_(True)
    (hash_jacobian_torch(x, t2, LAYOUT) * w).sum().backward()
    torch.testing.assert_close(t1.grad, t2.grad, rtol=1e-12, atol=1e-12)


def test_fused_encoding_and_jacobian_match_the_twins_with_one_table_gradient():
    t, x = table(), points()
    x[0] = torch.tensor([1.0, 0.5, 0.0], dtype=F64)  # on the cube's faces: J is 0, enc clamps
    x[1] = torch.tensor([1.3, -0.2, 0.5], dtype=F64)
    t1 = t.clone().requires_grad_(True)
    enc, jac = hash_encode_and_jacobian(x, t1, LAYOUT)
    t2 = t.clone().requires_grad_(True)
    enc_ref, jac_ref = hash_encode_torch(x, t2, LAYOUT), hash_jacobian_torch(x, t2, LAYOUT)
    torch.testing.assert_close(enc, enc_ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(jac, jac_ref, rtol=1e-12, atol=1e-12)
    assert (jac[:2] == 0).all()
    gen = torch.Generator().manual_seed(5)
    we = torch.randn(enc.shape, generator=gen, dtype=F64)
    wj = torch.randn(jac.shape, generator=gen, dtype=F64)
    ((enc * we).sum() + (jac * wj).sum()).backward()
    ((enc_ref * we).sum() + (jac_ref * wj).sum()).backward()
    torch.testing.assert_close(t1.grad, t2.grad, rtol=1e-12, atol=1e-12)


def test_fused_table_gradient_of_the_encoding_alone():
    """Only the encoding used (the Jacobian's gradient arrives as zeros): the table gradient is
    the encoding's, w_c summed per corner."""
    t, x = table(), points()
    t1 = t.clone().requires_grad_(True)
    hash_encode_and_jacobian(x, t1, LAYOUT)[0].sum().backward()
    t2 = t.clone().requires_grad_(True)
    hash_encode_torch(x, t2, LAYOUT).sum().backward()
    torch.testing.assert_close(t1.grad, t2.grad, rtol=1e-12, atol=1e-12)
