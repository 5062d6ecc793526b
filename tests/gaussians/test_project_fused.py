"""The fused numba projection + SH colour against its pure-torch twin (`project_splats_torch`):
outputs and hand-derived gradients of means, quaternions, log-scales and SH, float64."""

import math

import pytest
import torch

from recon.cameras import Cameras
from recon.gaussians.render import project_splats, project_splats_torch

F64 = torch.float64


def camera(W=64, H=48, f=50.0, cx=30.0, cy=26.0):
    K = torch.tensor([[[f, 0, cx], [0, f * 1.1, cy], [0, 0, 1]]], dtype=F64)
    angle = 0.3
    cfw = torch.eye(4, dtype=F64)[None].clone()
    cfw[0, :3, :3] = torch.tensor(
        [[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]],
        dtype=F64,
    )
    cfw[0, :3, 3] = torch.tensor([0.2, -0.1, 3.0])
    return Cameras(K, cfw, torch.tensor([W]), torch.tensor([H]))


def gaussians(G, degree, seed):
    gen = torch.Generator().manual_seed(seed)
    g = {
        "means": (torch.rand(G, 3, generator=gen, dtype=F64) - 0.5) * torch.tensor([8.0, 6.0, 7.0]),
        "quats": torch.randn(G, 4, generator=gen, dtype=F64),
        "log_scales": torch.log(0.02 + 0.5 * torch.rand(G, 3, generator=gen, dtype=F64)),
        "opacity_logits": torch.randn(G, generator=gen, dtype=F64),
        "sh_dc": torch.randn(G, 1, 3, generator=gen, dtype=F64),
        "sh_rest": torch.randn(G, 15, 3, generator=gen, dtype=F64) * 0.5,
    }
    g["quats"][0] = 0.0  # a zero quaternion
    g["means"][1] = torch.tensor([0.0, 0.0, -3.0])  # on the camera plane (camera z = 0)
    return g


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_fused_projection_matches_torch_twin(degree):
    cam = camera()
    g = {k: v.requires_grad_() for k, v in gaussians(300, degree, seed=degree).items()}
    fast, ref = project_splats(g, cam, degree), project_splats_torch(g, cam, degree)
    kept = ref.radii > 0
    assert 30 < int(kept.sum()) < 300  # some culled: behind, off-image, on the camera plane
    assert torch.equal(fast.radii, ref.radii)
    assert torch.allclose(fast.means2d[kept], ref.means2d[kept], rtol=1e-12)
    assert torch.allclose(fast.conics[kept], ref.conics[kept], rtol=1e-10, atol=1e-14)
    assert torch.allclose(fast.depths, ref.depths) and torch.allclose(fast.colors, ref.colors)
    assert (ref.colors == 0).any()  # the clamp at 0 is exercised
    gen = torch.Generator().manual_seed(7)
    weights = [
        torch.randn(t.shape, generator=gen, dtype=F64)
        for t in (ref.means2d, ref.conics, ref.depths, ref.colors)
    ]
    weights[0][~kept], weights[1][~kept] = 0.0, 0.0  # the rasterizer never sends these

    def loss(s):
        return sum(
            (w * t).sum() for w, t in zip(weights, (s.means2d, s.conics, s.depths, s.colors))
        )

    names = ["means", "quats", "log_scales", "sh_dc", "sh_rest"]
    g_fast = torch.autograd.grad(loss(fast), [g[n] for n in names], allow_unused=True)
    g_ref = torch.autograd.grad(loss(ref), [g[n] for n in names], allow_unused=True)
    for name, a, b in zip(names, g_fast, g_ref):
        if b is None:  # degree 0 never reads sh_rest
            assert a is None or not a.any(), name
            continue
        assert torch.isfinite(a).all(), name
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-9 * b.abs().max().item()), name


def test_guard_band_gradient_is_cut_like_the_twin():
    """Far outside the frustum but large enough to reach the image: x/z is clamped."""
    cam = camera()
    g = gaussians(2, 0, seed=3)
    g["means"] = torch.tensor([[-2.6, 0.0, 1.5], [2.0, 0.5, 1.0]], dtype=F64)
    g["log_scales"] = torch.full((2, 3), math.log(1.0), dtype=F64)
    g["quats"] = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, dtype=F64)
    g = {k: v.requires_grad_() for k, v in g.items()}
    fast, ref = project_splats(g, cam, 0), project_splats_torch(g, cam, 0)
    assert torch.equal(fast.radii, ref.radii) and bool((fast.radii > 0).all())
    out_f = fast.conics.sum() + fast.means2d.sum()
    out_r = ref.conics.sum() + ref.means2d.sum()
    for a, b in zip(
        torch.autograd.grad(out_f, [g["means"], g["log_scales"]]),
        torch.autograd.grad(out_r, [g["means"], g["log_scales"]]),
    ):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-12)


def test_float32_inputs_stay_float32():
    cam = camera()
    g = {k: v.float() for k, v in gaussians(50, 3, seed=4).items()}
    s = project_splats(g, cam, 3)
    assert s.means2d.dtype == torch.float32 and s.colors.dtype == torch.float32
    ref = project_splats_torch(g, cam, 3)
    kept = (s.radii > 0) & (ref.radii > 0)
    assert torch.allclose(s.means2d[kept], ref.means2d[kept], rtol=1e-5, atol=1e-3)


def camera_gradients(g, cam, degree, seed):
    """dL/d(cam_from_world) of a random linear loss of both projections' outputs."""
    cfw = cam.cam_from_world.clone().requires_grad_()
    cam = Cameras(cam.K, cfw, cam.width, cam.height)
    fast, ref = project_splats(g, cam, degree), project_splats_torch(g, cam, degree)
    kept = ref.radii > 0
    gen = torch.Generator().manual_seed(seed)
    weights = [
        torch.randn(t.shape, generator=gen, dtype=F64)
        for t in (ref.means2d, ref.conics, ref.depths, ref.colors)
    ]
    weights[0][~kept], weights[1][~kept] = 0.0, 0.0  # the rasterizer never sends these

    def loss(s):
        return sum(
            (w * t).sum() for w, t in zip(weights, (s.means2d, s.conics, s.depths, s.colors))
        )

    (d_fast,) = torch.autograd.grad(loss(fast), cfw)
    (d_ref,) = torch.autograd.grad(loss(ref), cfw)
    return d_fast[0], d_ref[0], kept


@pytest.mark.parametrize("degree", [0, 3])
def test_camera_gradient_matches_torch_twin(degree):
    """Random Gaussians: culled ones (behind, off-image, on the camera plane, zero quaternion),
    SH degree 3 colours whose view directions move with the camera centre."""
    cam = camera()
    g = gaussians(300, degree, seed=10 + degree)
    d_fast, d_ref, kept = camera_gradients(g, cam, degree, seed=11)
    assert 30 < int(kept.sum()) < 300
    assert torch.isfinite(d_fast).all() and not d_fast[3].any()
    assert d_ref[:3].abs().min() > 0  # every entry of the 3 x 4 block gets a gradient
    assert torch.allclose(d_fast, d_ref, rtol=1e-9, atol=1e-10 * d_ref.abs().max().item())


def test_camera_gradient_near_the_guard_band():
    """Gaussians straddling the clamp of x/z and y/z (inside, just outside, far outside but still
    reaching the image): the clamp cuts the same gradient paths in both."""
    cam = camera()
    fx, cx = float(cam.K[0, 0, 0]), float(cam.K[0, 0, 2])
    fy, cy = float(cam.K[0, 1, 1]), float(cam.K[0, 1, 2])
    W, H = int(cam.width[0]), int(cam.height[0])
    u_max = (W - cx) / fx + 0.15 * W / fx  # the guard band: 1.3 x the half field of view
    v_min = -cy / fy - 0.15 * H / fy
    z = 2.0
    u_values = torch.tensor([0.9, 0.99, 1.0, 1.01, 1.2]) * u_max
    v_values = torch.tensor([0.9, 0.99, 1.01, 1.2, 0.5]) * v_min
    points_in_cam = torch.stack([u_values * z, v_values * z, torch.full((5,), z)], -1).double()
    cfw = cam.cam_from_world[0]
    means = (points_in_cam - cfw[:3, 3]) @ cfw[:3, :3]  # world = R^T (p - t)
    g = gaussians(5, 3, seed=12)
    g["means"] = means
    g["log_scales"] = torch.full((5, 3), math.log(0.6), dtype=F64)
    d_fast, d_ref, kept = camera_gradients(g, cam, 3, seed=13)
    assert bool(kept.all())
    assert torch.allclose(d_fast, d_ref, rtol=1e-9, atol=1e-10 * d_ref.abs().max().item())


def test_no_camera_gradient_unless_asked():
    """Asking for the camera gradient leaves the Gaussians' gradients bit-identical."""
    cam = camera()
    names = ["means", "quats", "log_scales", "sh_dc", "sh_rest"]
    g = {k: v.requires_grad_(k in names) for k, v in gaussians(200, 3, seed=14).items()}
    cfw = cam.cam_from_world.clone().requires_grad_()
    grads = []
    for c in (cam, Cameras(cam.K, cfw, cam.width, cam.height)):
        s = project_splats(g, c, 3)
        loss = s.means2d.sum() + s.conics.sum() + s.colors.sum() + s.depths.sum()
        grads.append(torch.autograd.grad(loss, [g[n] for n in names]))
    for a, b in zip(*grads):
        assert torch.equal(a, b)
