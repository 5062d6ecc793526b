"""End to end from 3D parameters: projection + SH + fast rasterizer against the same projection
+ the dense twin, on outputs and on gradients of means, quaternions, scales, opacities, SH."""

import math

import torch

from recon.cameras import Cameras
from recon.gaussians.projection import antialias_compensation
from recon.gaussians.rasterize import rasterize_features
from recon.gaussians.rasterize_reference import rasterize_features_reference
from recon.gaussians.render import (
    composite_rgbd,
    mean_compensation,
    project_splats,
    project_splats_torch,
)

F64 = torch.float64


def camera(W=40, H=32, f=40.0):
    K = torch.tensor([[[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]]], dtype=F64)
    cfw = torch.eye(4, dtype=F64)[None].clone()
    cfw[0, :3, 3] = torch.tensor([0.1, -0.05, 3.0])
    return Cameras(K, cfw, torch.tensor([W]), torch.tensor([H]))


def random_gaussians(G, seed=0, degree=3):
    gen = torch.Generator().manual_seed(seed)
    return {
        "means": (torch.rand(G, 3, generator=gen, dtype=F64) - 0.5) * 2.4,
        "quats": torch.randn(G, 4, generator=gen, dtype=F64),
        "log_scales": torch.log(0.05 + 0.25 * torch.rand(G, 3, generator=gen, dtype=F64)),
        "opacity_logits": torch.randn(G, generator=gen, dtype=F64) * 2,
        "sh_dc": torch.randn(G, 1, 3, generator=gen, dtype=F64) * 0.3,
        "sh_rest": torch.randn(G, (degree + 1) ** 2 - 1, 3, generator=gen, dtype=F64) * 0.3,
    }


def render_with(rasterizer, gaussians, cam, degree=3):
    s = project_splats(gaussians, cam, degree)
    features = torch.cat([s.colors, s.depths[:, None]], -1)
    return rasterizer(
        s.means2d, s.conics, s.opacities, features, s.radii, s.depths, s.width, s.height
    )


def test_gradients_of_every_parameter_match_the_reference():
    cam = camera()
    params = {k: v.requires_grad_() for k, v in random_gaussians(40).items()}
    fast = render_with(rasterize_features, params, cam)
    ref = render_with(rasterize_features_reference, params, cam)
    assert torch.allclose(fast[0], ref[0], atol=1e-10) and torch.allclose(
        fast[1], ref[1], atol=1e-10
    )
    gen = torch.Generator().manual_seed(1)
    w_img = torch.randn(fast[0].shape, generator=gen, dtype=F64)
    w_T = torch.randn(fast[1].shape, generator=gen, dtype=F64)
    names = list(params)
    g_fast = torch.autograd.grad(
        (fast[0] * w_img).sum() + (fast[1] * w_T).sum(), list(params.values())
    )
    g_ref = torch.autograd.grad(
        (ref[0] * w_img).sum() + (ref[1] * w_T).sum(), list(params.values())
    )
    for name, a, b in zip(names, g_fast, g_ref):
        assert torch.isfinite(a).all() and b.abs().max() > 0, name
        assert torch.allclose(a, b, atol=1e-9 * max(1.0, b.abs().max().item()), rtol=0), name


def test_depth_channel_is_expected_z_and_acc_normalizes_it():
    """One large opaque splat straight ahead at camera z = 2: rgb = w c + T bg, depth / acc = 2."""
    cam = camera()
    g = {
        "means": torch.tensor([[-0.1, 0.05, -1.0]], dtype=F64),  # camera z = 3 - 1 = 2
        "quats": torch.tensor([[1.0, 0, 0, 0]], dtype=F64),
        "log_scales": torch.full((1, 3), math.log(0.5), dtype=F64),
        "opacity_logits": torch.tensor([4.0], dtype=F64),
        "sh_dc": torch.zeros(1, 1, 3, dtype=F64),
        "sh_rest": torch.zeros(1, 0, 3, dtype=F64),
    }
    s = project_splats(g, cam, 0)
    out = composite_rgbd(s, torch.tensor([1.0, 0.0, 0.0], dtype=F64))
    acc = out["acc"]
    assert float(acc[16, 20]) > 0.9
    hit = acc > 0
    assert torch.allclose(out["depth"][hit] / acc[hit], torch.full_like(acc[hit], 2.0))
    expected_rgb = 0.5 * acc[..., None] + (1 - acc)[..., None] * torch.tensor(
        [1.0, 0, 0], dtype=F64
    )
    assert torch.allclose(out["rgb"], expected_rgb)


def test_antialiased_opacities_are_compensated_alike_on_both_paths():
    """The fused CPU projection and its torch twin give the same compensated opacities and
    gradients; the factor is antialias_compensation of the conics, below 1 everywhere."""
    cam = camera()
    params = {k: v.requires_grad_() for k, v in random_gaussians(30, seed=4).items()}
    fused = project_splats(params, cam, 3, antialiased=True)
    twin = project_splats_torch(params, cam, 3, antialiased=True)
    plain = project_splats(params, cam, 3)
    seen = fused.radii > 0
    assert seen.sum() > 10
    assert torch.allclose(fused.opacities[seen], twin.opacities[seen], atol=1e-10)
    factor = antialias_compensation(plain.conics)
    assert torch.allclose(fused.opacities, plain.opacities * factor)
    assert (factor[seen] < 1).all() and (factor[seen] > 0).all()
    g_fused = torch.autograd.grad(
        fused.opacities[seen].sum(), list(params.values()), allow_unused=True
    )
    g_twin = torch.autograd.grad(
        twin.opacities[seen].sum(), list(params.values()), allow_unused=True
    )
    for name, a, b in zip(params, g_fused, g_twin):
        if b is None:
            assert a is None or a.abs().max() == 0, name
            continue
        assert torch.allclose(a, b, atol=1e-9 * max(1.0, b.abs().max().item())), name


def test_mean_compensation_averages_over_the_views_that_see_each_gaussian():
    """Brute-force twin: per view the compensated / plain opacity of `project_splats`, averaged
    over the views with radius > 0; a Gaussian behind every camera keeps 1. A view 4x farther
    (focal length / 4) shrinks the splats, so its factors are smaller."""
    g = random_gaussians(20, seed=6)
    g["means"][0] = torch.tensor([0.0, 0.0, -10.0], dtype=F64)  # behind both cameras (z < 0)
    near, far = camera(), camera(f=10.0)
    cams = Cameras(
        torch.cat([near.K, far.K]),
        torch.cat([near.cam_from_world, far.cam_from_world]),
        torch.cat([near.width, far.width]),
        torch.cat([near.height, far.height]),
    )
    total, seen = torch.zeros(20, dtype=F64), torch.zeros(20, dtype=F64)
    for view in range(2):
        plain = project_splats(g, cams[view], 0)
        aa = project_splats(g, cams[view], 0, antialiased=True)
        visible = plain.radii > 0
        total += torch.where(visible, aa.opacities / plain.opacities, 0.0)
        seen += visible.double()
    expected = torch.where(seen > 0, total / seen.clamp_min(1), 1.0)
    got = mean_compensation(g, cams, 0.01)
    assert torch.allclose(got, expected, atol=1e-12)
    assert got[0] == 1.0 and seen[0] == 0
    assert (got[1:][seen[1:] > 0] < 1).all()
    only_near = mean_compensation(g, cams[0], 0.01)
    both = seen == 2
    assert both.sum() > 5 and (got[both] < only_near[both]).all()
