"""Gaussian hard cases through the PRODUCTION path (the fused numba projection + the tile
rasterizer used in training), checked against the pure-torch twin on outputs and gradients:
zero-norm quaternion, scales 1e-8 and 1e3 (covers the whole image), a centre on the camera
plane, behind the camera, straddling and inside the near plane; 1 Gaussian; 10^6 Gaussians
(projection only). The torch twin's own limits (conic at det ~1e-12 / 1e12, guard band, EWA vs
autograd Jacobian) are in tests/gaussians/test_projection.py and test_gaussians_rasterize.py."""

import math

import pytest
import torch

from recon.cameras import Cameras
from recon.gaussians.project_fused import project_fused
from recon.gaussians.render import composite_rgbd, project_splats, project_splats_torch

F64 = torch.float64
W = H = 32
NEAR = 0.01


def camera() -> Cameras:
    K = torch.tensor([[[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]]], dtype=F64)
    return Cameras(K, torch.eye(4, dtype=F64)[None], torch.tensor([W]), torch.tensor([H]))


# name: (mean, quaternion, scale, culled)
HARD = {
    "zero-norm quaternion": ((0.0, 0.0, 2.0), (0.0, 0, 0, 0), 0.1, False),
    "scale 1e-8": ((0.1, 0.0, 2.0), (0.9, 0.1, 0.2, 0.3), 1e-8, False),
    "scale 1e3, covers the image": ((0.0, 0.1, 3.0), (0.7, 0.7, 0, 0), 1e3, False),
    "on the camera plane": ((0.1, 0.1, 0.0), (1.0, 0, 0, 0), 0.1, True),
    "behind the camera": ((0.0, 0.0, -1.0), (1.0, 0, 0, 0), 0.1, True),
    "inside the near plane": ((0.0, 0.0, 0.005), (1.0, 0, 0, 0), 0.1, True),
    "straddles the near plane": ((0.0, 0.05, 0.05), (1.0, 0, 0, 0), 0.2, False),
}


def gaussians(means, quats, scales, degree=1, seed=0):
    g = torch.Generator().manual_seed(seed)
    G = means.shape[0]
    return {
        "means": means,
        "quats": quats,
        "log_scales": torch.log(scales)[:, None].expand(G, 3).clone(),
        "opacity_logits": torch.full((G,), 2.0, dtype=F64),
        "sh_dc": torch.rand(G, 1, 3, generator=g, dtype=F64),
        "sh_rest": 0.1 * torch.randn(G, (degree + 1) ** 2 - 1, 3, generator=g, dtype=F64),
    }


def hard_set():
    means, quats, scales, culled = zip(*HARD.values())
    g = gaussians(
        torch.tensor(means, dtype=F64),
        torch.tensor(quats, dtype=F64),
        torch.tensor(scales, dtype=F64),
    )
    return {k: v.requires_grad_() for k, v in g.items()}, torch.tensor(culled)


def splat_outputs(s):
    return [s.means2d, s.conics, s.depths, s.colors]


def test_fused_projection_matches_the_torch_twin_on_every_hard_case():
    g, culled = hard_set()
    fused, twin = project_splats(g, camera(), 1, NEAR), project_splats_torch(g, camera(), 1, NEAR)
    assert ((fused.radii == 0) == culled).all(), dict(zip(HARD, fused.radii.tolist()))
    assert ((twin.radii == 0) == culled).all()
    keep = ~culled
    torch.testing.assert_close(fused.radii[keep], twin.radii[keep])
    for a, b in zip(splat_outputs(fused), splat_outputs(twin)):
        assert torch.isfinite(a).all()
        torch.testing.assert_close(a[keep], b[keep], rtol=1e-9, atol=1e-9)
    assert float(fused.radii[2]) > 10 * W  # the 1e3-scale splat covers the whole image
    # gradients of the kept Gaussians agree; every gradient is finite
    weights = [
        torch.randn(t.shape, generator=torch.Generator().manual_seed(i), dtype=F64)
        * keep.view(-1, *[1] * (t.dim() - 1))
        for i, t in enumerate(splat_outputs(fused))
    ]
    loss_f = sum((w * t).sum() for w, t in zip(weights, splat_outputs(fused)))
    loss_t = sum((w * t).sum() for w, t in zip(weights, splat_outputs(twin)))
    params = [g["means"], g["quats"], g["log_scales"], g["sh_dc"], g["sh_rest"]]
    for gf, gt in zip(torch.autograd.grad(loss_f, params), torch.autograd.grad(loss_t, params)):
        assert torch.isfinite(gf).all()
        torch.testing.assert_close(gf[keep], gt[keep], rtol=1e-6, atol=1e-8)


def test_rendering_the_hard_set_gives_finite_images_and_gradients():
    g, _ = hard_set()
    out = composite_rgbd(project_splats(g, camera(), 1, NEAR), torch.ones(3, dtype=F64))
    assert all(torch.isfinite(v).all() for v in out.values())
    assert float(out["acc"].detach().min()) > 0.5  # the image-covering splat reaches every pixel
    loss = out["rgb"].square().sum() + out["depth"].sum()
    grads = torch.autograd.grad(loss, list(g.values()))
    assert all(torch.isfinite(t).all() for t in grads)
    assert float(grads[0].abs().sum()) > 0


def test_one_gaussian_renders_its_own_weight():
    g = gaussians(
        torch.tensor([[0.0, 0, 2]], dtype=F64),
        torch.tensor([[1.0, 0, 0, 0]], dtype=F64),
        torch.tensor([0.05], dtype=F64),
        degree=0,
    )
    s = project_splats(g, camera(), 0, NEAR)
    out = composite_rgbd(s, torch.zeros(3, dtype=F64))
    # at the pixel nearest the centre: alpha = sigmoid(2) exp(-d^T conic d / 2), d = (0.5, 0.5) px off
    a, b, c = s.conics[0].tolist()
    alpha = torch.sigmoid(torch.tensor(2.0, dtype=F64)) * math.exp(
        -0.5 * (0.25 * a + 0.5 * b + 0.25 * c)
    )
    torch.testing.assert_close(out["acc"][H // 2, W // 2], alpha)
    torch.testing.assert_close(out["rgb"][H // 2, W // 2], alpha * s.colors[0])


@pytest.mark.usefixtures("one_thread")
def test_a_million_gaussians_project_finitely_and_match_the_twin_on_a_sample():
    G = 10**6
    gen = torch.Generator().manual_seed(0)
    means = torch.randn(G, 3, generator=gen, dtype=F64) * torch.tensor([1.0, 1.0, 2.0], dtype=F64)
    quats = torch.randn(G, 4, generator=gen, dtype=F64)
    quats[::1000] = 0.0  # some degenerate quaternions among them
    scales = torch.exp(
        torch.empty(G, dtype=F64).uniform_(math.log(1e-8), math.log(1e3), generator=gen)
    )
    g = gaussians(means, quats, scales, degree=0)
    K, cfw = camera().K[0], torch.eye(4, dtype=F64)
    with torch.no_grad():
        m2d, conics, depths, radii, colors = project_fused(
            g["means"], g["quats"], g["log_scales"], g["sh_dc"], g["sh_rest"], 0, K, cfw, W, H, NEAR
        )
    assert all(torch.isfinite(t).all() for t in (m2d, conics, depths, radii, colors))
    kept = radii > 0
    assert 0.1 < float(kept.double().mean()) < 0.9  # behind / outside ones culled, others kept
    assert not kept[means[:, 2] <= NEAR].any()
    idx = torch.arange(0, G, 997)
    sub = {k: v[idx] for k, v in g.items()}
    twin = project_splats_torch(sub, camera(), 0, NEAR)
    torch.testing.assert_close(radii[idx], twin.radii)
    k = kept[idx]
    torch.testing.assert_close(m2d[idx][k], twin.means2d[k], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(conics[idx][k], twin.conics[k], rtol=1e-9, atol=1e-12)
