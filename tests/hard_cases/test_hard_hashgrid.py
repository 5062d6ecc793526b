"""Hash grid at its largest: a 2^24-entry table and resolutions up to 2^30, so that
y * 2654435761 and z * 805459861 approach 2^61. The numba kernel and the torch twin must both
index exactly the row a Python big-int hash gives (no int64 or float overflow/rounding).
Points sit exactly on grid vertices, so the encoding returns the table row itself; with
table[row] = row (exact in float32 below 2^24) it returns the row index."""

import random

import torch

from recon.fields.hashgrid import _HashEncodeCPU, hash_encode_torch, level_layout

T = 2**24


def python_hash(x: int, y: int, z: int) -> int:
    return (x ^ (y * 2654435761) ^ (z * 805459861)) % T


def vertices(n: int, count: int, seed: int) -> list[list[int]]:
    rng = random.Random(seed)
    vs = [[rng.randrange(0, n) for _ in range(3)] for _ in range(count)]
    return vs + [
        [0, 0, 0],
        [n - 1, n - 1, n - 1],
        [n - 1, 0, n - 1],
    ]  # box corners (x = 1 uses cell n-1)


def row_table() -> torch.Tensor:
    return torch.arange(T, dtype=torch.float32)[:, None]  # (T, 1): feature = row index


def test_numba_kernel_on_a_2_24_table_matches_python_big_ints():
    n = 2**21  # vertex / n is exact in float32 for vertices < 2^24
    layout = level_layout(1, n, n, T)
    assert layout["dense"] == [False] and layout["size"] == [T]
    vs = vertices(n, 3000, 0)
    x = torch.tensor(vs, dtype=torch.float64).div(n).float()
    got = _HashEncodeCPU.apply(x, row_table(), layout)[:, 0]
    assert got.tolist() == [float(python_hash(*v)) for v in vs]


def test_torch_twin_at_resolution_2_30_matches_python_big_ints():
    n = 2**30
    layout = level_layout(1, n, n, T)
    vs = vertices(n, 3000, 1)
    x = torch.tensor(vs, dtype=torch.float64) / n  # exact in float64
    got = hash_encode_torch(x, row_table(), layout)[:, 0]
    assert got.tolist() == [float(python_hash(*v)) for v in vs]


def test_faces_corners_and_outside_points_on_a_huge_level_are_finite_with_gradients():
    n = 2**20
    layout = level_layout(2, n // 4, n, 2**18)  # two hashed levels at per-level offsets
    table = torch.randn(sum(layout["size"]), 2, dtype=torch.float64, requires_grad=True)
    x = torch.tensor(
        [
            [0.0, 0, 0],
            [1, 1, 1],
            [0.5, 0.25, 1.0],
            [3 / n, 1, 0],
            [-0.5, 2.0, 0.5],
            [1e-300, 1 - 1e-16, 0.5],
        ],
        dtype=torch.float64,
        requires_grad=True,
    )
    out = hash_encode_torch(x, table, layout)
    assert torch.isfinite(out).all()
    g_x, g_t = torch.autograd.grad(out.sum(), [x, table])
    assert torch.isfinite(g_x).all() and torch.isfinite(g_t).all()
    # outside the box clamps to the face: same features as the clamped point
    torch.testing.assert_close(
        out[4], hash_encode_torch(x[4:5].detach().clamp(0, 1), table, layout)[0]
    )
    # the 8 corner weights of a point sum to 1 on each level: d(sum)/d(table) sums to N L F
    assert abs(float(g_t.sum()) - x.shape[0] * 2 * 2) < 1e-9
