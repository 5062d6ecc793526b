"""The numba tile rasterizer against its dense pure-torch twin (outputs and gradients, float64),
the binning against the global key sort, gradcheck, the weight rule and hard cases."""

import math

import pytest
import torch

from recon.gaussians import rasterize
from recon.gaussians.projection import conic_from_cov2d, radius_3sigma
from recon.gaussians.rasterize import ALPHA_MAX, T_MIN, rasterize_features
from recon.gaussians.rasterize_reference import rasterize_features_reference
from recon.gaussians.rasterize_torch import rasterize_features_torch
from recon.gaussians.tiles import (
    TILE,
    TILE_LARGE,
    alpha_extent,
    bin_gaussians,
    bin_gaussians_sorted,
    stable_argsort,
    tile_bounds,
    tile_size,
)

F64 = torch.float64


def random_splats(G, W, H, D=3, seed=0, opacity=(0.0, 1.0), sigma=3.0, dtype=F64):
    """Random 2D splats, some partly or fully off-image; conics from random SPD covariances."""
    gen = torch.Generator().manual_seed(seed)
    means2d = torch.rand(G, 2, generator=gen, dtype=dtype) * torch.tensor([W, H]) * 1.3 - 5
    L = torch.randn(G, 2, 2, generator=gen, dtype=dtype) * sigma
    cov = L @ L.transpose(1, 2) + 0.3 * torch.eye(2, dtype=dtype)
    packed = torch.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]], -1)
    conics = conic_from_cov2d(packed)[0]
    lo, hi = opacity
    opacities = lo + (hi - lo) * torch.rand(G, generator=gen, dtype=dtype)
    features = torch.rand(G, D, generator=gen, dtype=dtype)
    depths = torch.rand(G, generator=gen, dtype=dtype) * 5
    return means2d, conics, opacities, features, radius_3sigma(packed), depths


def compare(splats, W, H, atol=1e-10):
    """Outputs and gradients (means2d, conics, opacities, features) of fast vs reference."""
    means2d, conics, opacities, features, radii, depths = splats
    leaves = [t.clone().requires_grad_() for t in (means2d, conics, opacities, features)]
    fast = rasterize_features(*leaves, radii, depths, W, H)
    ref = rasterize_features_reference(*leaves, radii, depths, W, H)
    for a, b in zip(fast, ref):
        assert torch.allclose(a, b, atol=atol, rtol=0), (a - b).abs().max()
    gen = torch.Generator().manual_seed(123)
    g_img = torch.randn(fast[0].shape, generator=gen, dtype=fast[0].dtype)
    g_T = torch.randn(fast[1].shape, generator=gen, dtype=fast[1].dtype)
    grads = [
        torch.autograd.grad((out[0] * g_img).sum() + (out[1] * g_T).sum(), leaves)
        for out in (fast, ref)
    ]
    for name, a, b in zip(["means2d", "conics", "opacities", "features"], *grads):
        scale = b.abs().max().clamp_min(1.0)
        assert torch.allclose(a, b, atol=atol * scale, rtol=0), (name, (a - b).abs().max())
    return fast, ref


@pytest.mark.parametrize(
    "G, W, H, D, seed",
    [(60, 37, 29, 3, 0), (200, 48, 32, 4, 1), (30, 16, 16, 1, 2), (120, 50, 21, 3, 3)],
)
def test_fast_matches_reference_outputs_and_gradients(G, W, H, D, seed):
    compare(random_splats(G, W, H, D, seed), W, H)


def test_opaque_stack_terminates_early_like_the_reference():
    """Many near-opaque splats over every pixel: transmittance stops before 1e-4."""
    splats = random_splats(80, 40, 24, seed=4, opacity=(0.9, 1.0), sigma=8.0)
    (_image, T), _ = compare(splats, 40, 24)
    covered = T < 0.5
    assert covered.float().mean() > 0.5
    assert (T >= T_MIN).all() and (T[covered] < 1e-2).any()


def test_float32_matches_float64_reference():
    splats = random_splats(100, 33, 40, seed=5)
    fast = rasterize_features(*[t.float() for t in splats[:4]], splats[4], splats[5], 33, 40)
    ref = rasterize_features_reference(*splats, 33, 40)
    assert torch.allclose(fast[0].double(), ref[0], atol=1e-4)
    assert torch.allclose(fast[1].double(), ref[1], atol=1e-4)


def test_gradcheck_fast_rasterizer():
    means2d, conics, opacities, features, radii, depths = random_splats(
        4, 12, 10, D=2, seed=6, opacity=(0.3, 0.9), sigma=2.0
    )
    means2d = means2d * 0.5 + 2  # keep them on the small image

    def fn(m, c, o, f):
        image, T = rasterize_features(m, c, o, f, radii, depths, 12, 10)
        return image, T

    inputs = [t.clone().requires_grad_() for t in (means2d, conics, opacities, features)]
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-7, atol=1e-5)


def test_single_splat_weight_rule():
    """One splat of opacity o centred on a pixel centre: F = o f there, T = 1 - o; and a pixel
    at offset d gets alpha = o exp(-0.5 d^T conic d)."""
    means2d = torch.tensor([[8.5, 4.5]], dtype=F64)
    cov = torch.tensor([[4.0, 1.0, 2.0]], dtype=F64)
    conics = conic_from_cov2d(cov)[0]
    o, f = 0.6, torch.tensor([[0.2, 0.4, 0.8]], dtype=F64)
    image, T = rasterize_features(
        means2d,
        conics,
        torch.tensor([o], dtype=F64),
        f,
        radius_3sigma(cov),
        torch.ones(1, dtype=F64),
        16,
        8,
    )
    assert torch.allclose(image[4, 8], o * f[0]) and math.isclose(float(T[4, 8]), 1 - o)
    A, B, C = conics[0].tolist()
    dx, dy = 8.5 - 10.5, 4.5 - 5.5  # pixel (x=10, y=5)
    alpha = o * math.exp(-0.5 * (A * dx * dx + 2 * B * dx * dy + C * dy * dy))
    assert math.isclose(float(T[5, 10]), 1 - alpha, rel_tol=1e-12)


def test_alpha_is_clamped_and_faint_splats_skipped():
    means2d = torch.tensor([[4.5, 4.5], [28.5, 4.5]], dtype=F64)
    cov = torch.tensor([[2.0, 0.0, 2.0]] * 2, dtype=F64)
    conics = conic_from_cov2d(cov)[0]
    opac = torch.tensor([1.0, 0.5 / 255], dtype=F64)  # clamped to 0.99 | below 1/255: skipped
    _image, T = rasterize_features(
        means2d,
        conics,
        opac,
        torch.ones(2, 1, dtype=F64),
        radius_3sigma(cov),
        torch.ones(2, dtype=F64),
        32,
        8,
    )
    assert float(T.min()) == pytest.approx(1 - ALPHA_MAX)
    assert torch.all(T[:, 20:] == 1.0)


def test_one_gaussian_and_one_covering_the_whole_image():
    W, H = 40, 30
    splats = random_splats(1, W, H, seed=7)
    compare(splats, W, H)
    means2d = torch.tensor([[20.0, 15.0], [5.0, 5.0]], dtype=F64)
    cov = torch.tensor([[1e6, 3e5, 1e6], [3.0, 0.5, 2.0]], dtype=F64)  # det ~1e12 | small
    conics = conic_from_cov2d(cov)[0]
    splats = (
        means2d,
        conics,
        torch.tensor([0.7, 0.9], dtype=F64),
        torch.rand(2, 3, dtype=F64),
        radius_3sigma(cov),
        torch.tensor([2.0, 1.0], dtype=F64),
    )
    (_image, T), _ = compare(splats, W, H)
    assert (T < 1).all()  # the big one reaches every pixel


def test_near_singular_2d_covariance():
    """det(Sigma') ~ 1e-12: a needle-thin splat (huge conic) is rasterized finitely and matches."""
    means2d = torch.tensor([[10.3, 7.7]], dtype=F64)
    cov = torch.tensor([[1e-6, 0.0, 1e-6]], dtype=F64)
    conics = conic_from_cov2d(cov)[0]
    assert conics[0, 0] == pytest.approx(1e6)
    splats = (
        means2d,
        conics,
        torch.tensor([0.8], dtype=F64),
        torch.ones(1, 3, dtype=F64),
        torch.tensor([3.0], dtype=F64),
        torch.ones(1, dtype=F64),
    )
    compare(splats, 20, 16)


def test_culled_splats_contribute_nothing():
    splats = list(random_splats(50, 32, 32, seed=8))
    splats[4] = torch.zeros_like(splats[4])
    image, T = rasterize_features(*splats, 32, 32)
    assert torch.equal(T, torch.ones_like(T)) and torch.equal(image, torch.zeros_like(image))


@pytest.mark.parametrize("seed", [0, 1])
def test_counting_sort_binning_equals_global_key_sort(seed):
    means2d, _, _, _, radii, depths = random_splats(300, 70, 45, seed=seed, sigma=6.0)
    depths[:10] = 1.0  # ties keep their index order in both
    bounds = tile_bounds(means2d, radii, 70, 45, TILE)
    starts_a, ids_a = bin_gaussians(bounds, depths, 70, 45, TILE)
    starts_b, ids_b = bin_gaussians_sorted(bounds, depths, 70, 45, TILE)
    assert torch.equal(starts_a, starts_b) and torch.equal(ids_a, ids_b)
    for t in range(len(starts_a) - 1):  # each tile's list is front to back
        d = depths[ids_a[starts_a[t] : starts_a[t + 1]]]
        assert torch.all(d[1:] >= d[:-1])


def test_tile_bounds_worked_example():
    bounds = tile_bounds(
        torch.tensor([[20.0, 5.0], [-50.0, 5.0]]), torch.tensor([3.0, 3.0]), 64, 64, TILE
    )
    assert bounds[0].tolist() == [1, 0, 2, 1]
    assert bounds[1, 0] == bounds[1, 2]  # entirely left of the image: no tiles


def test_alpha_extent_worked_example():
    """conic (1, 0, 4), o = 1: Q <= q = 2 ln 255 (1 + 1e-3) + 2e-3 -> half sides sqrt(q),
    sqrt(q) / 2; o below 1/255 -> -1; an indefinite conic -> inf."""
    e = alpha_extent(
        torch.tensor([[1.0, 0.0, 4.0], [1.0, 0.0, 4.0], [1.0, 2.0, 1.0]]),
        torch.tensor([1.0, 0.003, 0.5]),
    )
    q = 2 * math.log(255) * 1.001 + 0.002
    assert torch.allclose(e[0], torch.tensor([math.sqrt(q), math.sqrt(q) / 2], dtype=F64))
    assert math.isclose(float(e[0, 0]), 3.3310, abs_tol=1e-4)
    assert e[1].tolist() == [-1.0, -1.0] and torch.isinf(e[2]).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_alpha_bounds_drop_only_tiles_no_pixel_of_the_splat_reaches(seed):
    """Boxes shrunk to the alpha >= 1/255 ellipse lie inside the 3-sigma boxes, hold every
    pixel where a splat's alpha reaches 1/255 inside its 3-sigma box, and rasterize to the
    same image bit for bit; on these splats they drop a third of the tile entries."""
    W, H = 70, 45
    means2d, conics, opacities, features, radii, depths = random_splats(
        300, W, H, seed=seed, sigma=6.0
    )
    loose = tile_bounds(means2d, radii, W, H, TILE)
    tight = tile_bounds(means2d, radii, W, H, TILE, conics, opacities)
    empty = (tight[:, 2] <= tight[:, 0]) | (tight[:, 3] <= tight[:, 1])
    inside = (tight[:, :2] >= loose[:, :2]) & (tight[:, 2:] <= loose[:, 2:])
    assert (empty | inside.all(1)).all()
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    centres = torch.stack([xs, ys], -1).reshape(-1, 2).to(F64) + 0.5
    d = centres[None] - means2d[:, None]
    A, B, C = conics.unbind(-1)
    power = -0.5 * (A[:, None] * d[..., 0] ** 2 + C[:, None] * d[..., 1] ** 2)
    power = power - B[:, None] * d[..., 0] * d[..., 1]
    reaches = opacities[:, None] * torch.exp(power) >= 1 / 255  # (G, pixels)
    tx, ty = (centres[:, 0] // TILE).long(), (centres[:, 1] // TILE).long()

    def listed(b):
        return (tx >= b[:, :1]) & (tx < b[:, 2:3]) & (ty >= b[:, 1:2]) & (ty < b[:, 3:4])

    assert not (reaches & listed(loose) & ~listed(tight)).any()
    size = lambda b: int(((b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])).clamp_min(0).sum())
    assert size(tight) < 0.8 * size(loose)
    images = []
    for bounds in (loose, tight):
        starts, ids = bin_gaussians(bounds, depths, W, H, TILE)
        images.append(
            rasterize._RasterizeFeatures.apply(
                means2d, conics, opacities, features, starts, ids, W, H, TILE, None
            )
        )
    assert all(torch.equal(a, b) for a, b in zip(*images))


def test_tile_size_grows_with_the_image():
    assert tile_size(200, 200) == TILE and tile_size(383, 384) == TILE
    assert tile_size(384, 384) == TILE_LARGE and tile_size(1913, 1076) == TILE_LARGE


def test_large_tiles_match_reference():
    """An image big enough for 32 px tiles: fast and packed torch rasterizers against the
    dense reference (which lists splats by the same tiles)."""
    W, H = 400, 390
    assert tile_size(W, H) == TILE_LARGE
    splats = random_splats(60, W, H, seed=9, sigma=12.0)
    compare(splats, W, H)
    packed = rasterize_features_torch(*splats, W, H)
    ref = rasterize_features_reference(*splats, W, H)
    for a, b in zip(packed, ref):
        assert torch.allclose(a, b, atol=1e-10)


@pytest.mark.parametrize("G, W, H, seed", [(60, 37, 29, 0), (150, 48, 32, 1)])
def test_packed_torch_rasterizer_matches_reference(G, W, H, seed):
    """The non-CPU path (segmented log-space cumsum over the tile lists), run on the CPU."""
    means2d, conics, opacities, features, radii, depths = random_splats(G, W, H, seed=seed)
    leaves = [t.clone().requires_grad_() for t in (means2d, conics, opacities, features)]
    packed = rasterize_features_torch(*leaves, radii, depths, W, H)
    ref = rasterize_features_reference(*leaves, radii, depths, W, H)
    for a, b in zip(packed, ref):
        assert torch.allclose(a, b, atol=1e-10)
    weights = [torch.randn(t.shape, dtype=F64) for t in ref]
    g_packed = torch.autograd.grad(sum((w * t).sum() for w, t in zip(weights, packed)), leaves)
    g_ref = torch.autograd.grad(sum((w * t).sum() for w, t in zip(weights, ref)), leaves)
    for a, b in zip(g_packed, g_ref):
        assert torch.allclose(a, b, atol=1e-9 * max(1.0, b.abs().max().item()))


def test_packed_rasterizer_terminates_early_like_the_reference():
    splats = random_splats(80, 40, 24, seed=4, opacity=(0.9, 1.0), sigma=8.0)
    packed = rasterize_features_torch(*splats, 40, 24)
    ref = rasterize_features_reference(*splats, 40, 24)
    assert torch.allclose(packed[0], ref[0], atol=1e-10)
    assert torch.allclose(packed[1], ref[1], atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_radix_argsort_equals_torch_stable_argsort(dtype):
    gen = torch.Generator().manual_seed(3)
    values = torch.randn(5000, generator=gen, dtype=dtype) * 10
    values[::7] = values[3]  # ties keep index order
    values[:5] = torch.tensor([0.0, -0.5, float("inf"), -float("inf"), 1e-30], dtype=dtype)
    expected = torch.argsort(values, stable=True)
    assert torch.equal(torch.from_numpy(stable_argsort(values.numpy())), expected)


def brute_force_abs_grad(splats, W, H, g_img, g_T):
    """sum_p |dL_p/dmu'| per splat, L_p = <g_img[p], F(p)> + g_T[p] T(p): one autograd pass of
    the dense reference per pixel."""
    means2d, conics, opacities, features, radii, depths = splats
    leaf = means2d.clone().requires_grad_()
    image, T = rasterize_features_reference(leaf, conics, opacities, features, radii, depths, W, H)
    total = torch.zeros_like(means2d)
    for py in range(H):
        for px in range(W):
            loss_p = (image[py, px] * g_img[py, px]).sum() + T[py, px] * g_T[py, px]
            (g,) = torch.autograd.grad(loss_p, leaf, retain_graph=True)
            total += g.abs()
    return total


@pytest.mark.parametrize("rasterizer", [rasterize_features, rasterize_features_torch])
def test_abs_grad_matches_per_pixel_brute_force(rasterizer):
    W, H = 14, 11
    splats = random_splats(12, W, H, seed=7, opacity=(0.3, 0.95), sigma=2.5)
    means2d, conics, opacities, features, radii, depths = splats
    gen = torch.Generator().manual_seed(8)
    g_img = torch.randn(H, W, 3, generator=gen, dtype=F64)
    g_T = torch.randn(H, W, generator=gen, dtype=F64)
    leaf = means2d.clone().requires_grad_()
    sink = torch.zeros_like(means2d)
    image, T = rasterizer(leaf, conics, opacities, features, radii, depths, W, H, sink)
    ((image * g_img).sum() + (T * g_T).sum()).backward()
    expected = brute_force_abs_grad(splats, W, H, g_img, g_T)
    assert expected.abs().max() > 0.1
    assert torch.allclose(sink, expected, atol=1e-9, rtol=1e-9), (sink - expected).abs().max()
    # the triangle inequality: |sum_p g_p| <= sum_p |g_p|, equality only without cancellation
    assert (leaf.grad.abs() <= sink + 1e-12).all()


def test_abs_grad_sees_a_symmetric_error_the_mean_gradient_cancels():
    """One round splat centred on a pixel centre, every pixel's error the same: the left and
    right halves pull the mean in opposite directions, so dL/dmu' = 0 while sum |.| > 0 (the
    case AbsGS densifies and the mean-gradient rule misses; Ye et al. 2024, Fig. 2)."""
    W = H = 9
    means2d = torch.tensor([[4.5, 4.5]], dtype=F64, requires_grad=True)
    conics = torch.tensor([[0.5, 0.0, 0.5]], dtype=F64)
    opacities = torch.tensor([0.8], dtype=F64)
    features = torch.tensor([[0.3]], dtype=F64)
    sink = torch.zeros(1, 2, dtype=F64)
    image, _ = rasterize_features(
        means2d,
        conics,
        opacities,
        features,
        torch.tensor([4.0]),
        torch.ones(1, dtype=F64),
        W,
        H,
        sink,
    )
    image.sum().backward()
    assert means2d.grad.abs().max() < 1e-12
    assert (sink > 1e-3).all()
