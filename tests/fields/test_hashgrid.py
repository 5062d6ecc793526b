"""Multiresolution hash encoding: the growth factor of Müller et al. 2022 (eq. 3), the hash against big-int arithmetic, the
numba kernel against the pure-torch twin (values and gradients), exactness of trilinear
interpolation, and points on faces, corners and the box corners."""

import random

import pytest
import torch

from recon.fields.hashgrid import (
    HashGrid,
    gather_rows,
    growth_factor,
    hash_encode,
    hash_encode_torch,
    level_layout,
    spatial_hash,
)


def test_hashgrid_layout_and_parameter_count_worked_example():
    assert growth_factor(16, 16, 2048) == pytest.approx(1.3819, abs=1e-4)
    lay = level_layout(16, 16, 2048, 2**19)
    assert lay["resolution"] == [
        16,
        22,
        30,
        42,
        58,
        80,
        111,
        153,
        212,
        294,
        406,
        561,
        776,
        1072,
        1482,
        2048,
    ]
    assert lay["dense"] == [True] * 5 + [False] * 11  # 81^3 = 531441 > 2^19 at level 5
    assert lay["size"][:5] == [4913, 12167, 29791, 79507, 205379]
    assert sum(lay["size"]) == 6_098_925
    grid = HashGrid(16, 2, 19, 16, 2048)
    assert grid.table.numel() == 12_197_850 and grid.out_dim == 32
    assert lay["offset"][5] == 331_757


def test_spatial_hash_matches_python_big_ints():
    rng = random.Random(0)
    T = 2**19
    verts = [[rng.randrange(0, 2**22) for _ in range(3)] for _ in range(2000)] + [
        [2**22, 2**22, 2**22]
    ]
    got = spatial_hash(torch.tensor(verts), T).tolist()
    for (x, y, z), h in zip(verts, got):
        assert h == ((x * 1) ^ (y * 2654435761) ^ (z * 805459861)) % T
    # a table size that is not a power of two (the numba kernel uses a mask only for powers of 2)
    got = spatial_hash(torch.tensor(verts), 1000003).tolist()
    assert all(
        h == ((x ^ (y * 2654435761) ^ (z * 805459861)) % 1000003)
        for (x, y, z), h in zip(verts, got)
    )


def slow_encode(x, table, lay, F):
    """Obviously-correct twin: Python loops over points, levels and corners."""
    out = torch.zeros(x.shape[0], len(lay["resolution"]) * F, dtype=table.dtype)
    for p in range(x.shape[0]):
        for lv, n in enumerate(lay["resolution"]):
            pos = [min(max(float(v), 0.0), 1.0) * n for v in x[p]]
            i0 = [min(int(v // 1), n - 1) for v in pos]
            f = [v - i for v, i in zip(pos, i0)]
            for c in range(8):
                b = [(c >> k) & 1 for k in range(3)]
                v = [i + bb for i, bb in zip(i0, b)]
                w = 1.0
                for k in range(3):
                    w *= f[k] if b[k] else 1 - f[k]
                if lay["dense"][lv]:
                    idx = v[0] + (n + 1) * v[1] + (n + 1) ** 2 * v[2]
                else:
                    idx = ((v[0] * 1) ^ (v[1] * 2654435761) ^ (v[2] * 805459861)) % lay["size"][lv]
                out[p, lv * F : (lv + 1) * F] += w * table[lay["offset"][lv] + idx]
    return out


@pytest.fixture(scope="module")
def small_grid():
    torch.manual_seed(0)
    grid = HashGrid(n_levels=6, n_features=2, log2_table_size=12, n_min=4, n_max=64)
    with torch.no_grad():
        grid.table.normal_()  # O(1) features so differences are visible
    assert any(grid.layout["dense"]) and not all(grid.layout["dense"])
    return grid


def special_points(lay):
    """Points exactly on cell faces/edges/corners of every level, the box corners, outside."""
    pts = [[0, 0, 0], [1, 1, 1], [1, 0, 1], [0.5, 0.5, 0.5], [1.2, -0.1, 0.5]]
    for n in lay["resolution"]:
        pts += [[3 / n, 0.3, 0.7], [1 / n, 2 / n, 5 / n], [(n - 1) / n, 1, 0]]
    return torch.tensor(pts, dtype=torch.float64)


def test_torch_twin_matches_slow_loops(small_grid):
    lay, table = small_grid.layout, small_grid.table.detach().double()
    x = torch.cat([torch.rand(20, 3, dtype=torch.float64), special_points(lay)])
    torch.testing.assert_close(hash_encode_torch(x, table, lay), slow_encode(x, table, lay, 2))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_numba_kernel_matches_torch_twin_values_and_grads(small_grid, dtype):
    lay = small_grid.layout
    x = torch.cat([torch.rand(3000, 3, dtype=torch.float64), special_points(lay)]).to(dtype)
    t1 = small_grid.table.detach().to(dtype).clone().requires_grad_()
    t2 = t1.detach().clone().requires_grad_()
    fast, ref = hash_encode(x, t1, lay), hash_encode_torch(x, t2, lay)
    tol = {"rtol": 1e-5, "atol": 1e-5} if dtype == torch.float32 else {"rtol": 1e-12, "atol": 1e-12}
    torch.testing.assert_close(fast, ref, **tol)
    g = torch.randn_like(fast)
    (fast * g).sum().backward()
    (ref * g).sum().backward()
    torch.testing.assert_close(t1.grad, t2.grad, **tol)


def test_trilinear_reproduces_linear_functions_on_dense_levels():
    # trilinear interpolation is exact for f(v) = a . v + c stored at the vertices
    lay = level_layout(3, 4, 9, 2**20)
    assert all(lay["dense"])
    table = torch.zeros(sum(lay["size"]), 1, dtype=torch.float64)
    a = torch.tensor([0.3, -1.2, 0.7], dtype=torch.float64)
    for lv, n in enumerate(lay["resolution"]):
        g = torch.arange(n + 1, dtype=torch.float64)
        z, y, xx = torch.meshgrid(g, g, g, indexing="ij")  # dense index x fastest
        v = torch.stack([xx, y, z], -1).reshape(-1, 3) / n
        table[lay["offset"][lv] : lay["offset"][lv] + (n + 1) ** 3, 0] = v @ a + 0.25
    x = torch.cat([torch.rand(200, 3, dtype=torch.float64), special_points(lay)[:4]])
    expected = (x @ a + 0.25)[:, None].expand(-1, 3)
    torch.testing.assert_close(hash_encode(x, table, lay), expected)
    torch.testing.assert_close(hash_encode_torch(x, table, lay), expected)


def test_continuous_across_cell_faces(small_grid):
    lay, table = small_grid.layout, small_grid.table.detach().double()
    for n in lay["resolution"]:
        face = torch.tensor([[5 / n, 0.37, 0.61]], dtype=torch.float64)
        e = torch.tensor([[1e-9, 0, 0]], dtype=torch.float64)
        lo, hi = hash_encode(face - e, table, lay), hash_encode(face + e, table, lay)
        assert (lo - hi).abs().max() < 1e-6


def test_gradcheck_positions_and_table_float64():
    # tiny table: gradcheck perturbs every entry; levels 2, 4 dense, 8 hashed into 64 slots
    lay = level_layout(3, 2, 8, 64)
    assert lay["dense"] == [True, False, False] or lay["dense"] == [True, True, False]
    table = torch.randn(sum(lay["size"]), 2, dtype=torch.float64, requires_grad=True)
    # keep points away from cell boundaries, where the encoding has a kink
    x = (
        torch.tensor([[0.113, 0.527, 0.801], [0.61, 0.29, 0.07]], dtype=torch.float64)
    ).requires_grad_()
    assert torch.autograd.gradcheck(lambda p, t: hash_encode_torch(p, t, lay), (x, table))
    assert torch.autograd.gradcheck(lambda t: hash_encode(x.detach(), t, lay), (table,))


def test_empty_batch(small_grid):
    table = small_grid.table.detach().clone().requires_grad_()
    out = hash_encode(torch.zeros(0, 3), table, small_grid.layout)
    assert out.shape == (0, 12)
    out.sum().backward()
    assert (table.grad == 0).all()


def test_gather_rows_is_advanced_indexing_values_and_gradients():
    """The gather's values and table gradient (repeated rows add up) equal table[rows]'s."""
    gen = torch.Generator().manual_seed(3)
    table = torch.randn(50, 2, dtype=torch.float64, generator=gen, requires_grad=True)
    rows = torch.randint(0, 50, (7, 3, 8), generator=gen)  # 168 rows of 50: many repeats
    upstream = torch.randn(7, 3, 8, 2, dtype=torch.float64, generator=gen)
    ours = gather_rows(table, rows)
    (g_ours,) = torch.autograd.grad((ours * upstream).sum(), table)
    ref = table[rows]
    (g_ref,) = torch.autograd.grad((ref * upstream).sum(), table)
    assert ours.shape == (7, 3, 8, 2) and torch.equal(ours, ref)
    assert torch.allclose(g_ours, g_ref, rtol=0, atol=1e-12)
    assert gather_rows(table, rows[:0]).shape == (0, 3, 8, 2)
