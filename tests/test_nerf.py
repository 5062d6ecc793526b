"""NeRF model: the paper's architecture, hierarchical sampling, learning an analytic sphere scene,
exact resume."""

import copy

import pytest
import torch
from test_ngp import eval_psnr, mean_colour_psnr, sphere_scene

from recon.models.base import METHODS, SceneInfo
from recon.models.nerf import PRESETS, NeRFConfig, NeRFMLP, NeRFModel

SMALL = NeRFConfig(depth=3, width=64, skip_layer=2, pos_bands=4, n_coarse=16, n_fine=16,
                   rays_per_batch=256, lr=5e-3, lr_final=5e-4, lr_decay_steps=150, chunk=1024)


pytestmark = pytest.mark.usefixtures("one_thread")


def test_paper_preset_is_the_paper_architecture():
    assert METHODS["nerf"].config_cls is NeRFConfig and set(PRESETS) == {"fast", "paper"}
    cfg = NeRFConfig(**PRESETS["paper"])
    assert (cfg.n_coarse, cfg.n_fine, cfg.rays_per_batch, cfg.pos_bands, cfg.dir_bands) == (64, 128, 4096, 10, 4)
    net = NeRFMLP(cfg)
    assert len(net.layers) == 8 and all(layer.out_features == 256 for layer in net.layers)
    ins = [layer.in_features for layer in net.layers]
    assert ins == [63, 256, 256, 256, 256, 256 + 63, 256, 256]  # input joins the 5th layer's output
    assert net.color[0].in_features == 256 + 27 and net.color[0].out_features == 128


def test_density_depends_on_position_only():
    net = NeRFMLP(SMALL)
    x = torch.randn(5, net.pos_dim)
    s1, c1 = net(x, torch.randn(5, 27))
    s2, c2 = net(x, torch.randn(5, 27))
    assert torch.equal(s1, s2) and not torch.equal(c1, c2) and (s1 >= 0).all()


def test_learns_sphere_and_renders():
    torch.manual_seed(0)
    data, info, depths = sphere_scene(8, 24)
    model = NeRFModel(SMALL, info)
    baseline = mean_colour_psnr(data.images)
    first = model.train_step(data, 0)
    for step in range(1, 150):
        stats = model.train_step(data, step)
    assert stats["loss"] < 0.2 * first["loss"]
    model.eval()
    out = model.render(data.cameras[0])
    assert out["rgb"].shape == (24, 24, 3) and out["depth"].shape == (24, 24) and out["acc"].shape == (24, 24)
    assert all(torch.isfinite(v).all() for v in out.values())
    assert eval_psnr(model, data) > baseline + 8
    hit = depths[0] > 0
    assert (out["depth"][hit] - depths[0][hit]).abs().median() < 0.25
    assert out["acc"][hit].mean() > 0.8 and out["acc"][~hit].mean() < 0.15


def test_fine_samples_concentrate_where_coarse_weight_is():
    _, info, _ = sphere_scene(2, 8)
    model = NeRFModel(SMALL, info)
    o = torch.tensor([[0.0, 0.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]])
    # a coarse network whose density is a thin slab at t = 2.5 (z = -0.5): patch its geometry
    model.coarse.geometry = lambda x_enc: (30.0 * ((x_enc[:, 2] + 0.5).abs() < 0.05).float(),
                                           torch.zeros(x_enc.shape[0], SMALL.width))
    model.cfg = NeRFConfig(**{**SMALL.__dict__, "n_coarse": 64, "n_fine": 64})
    seen = {}
    original = model._render_net

    def spy(net, o_, d_, t0, t1):
        seen[net is model.fine] = (t0, t1)
        return original(net, o_, d_, t0, t1)

    model._render_net = spy
    with torch.no_grad():
        model._render_rays(o, d, jitter=False)
    f0, f1 = seen[True]
    mids = 0.5 * (f0 + f1)[0]
    near_slab = ((mids - 2.5).abs() < 0.1).sum().item()
    assert near_slab >= 64  # all the fine samples land around the slab (coarse ones are spread)


def test_resume_is_exact():
    data, info, _ = sphere_scene(n_cams=3, size=12)
    a = NeRFModel(SMALL, info)
    for step in range(5):
        a.train_step(data, step)
    b = NeRFModel(SMALL, info)
    b.load_state_dict(copy.deepcopy(a.state_dict()))
    b.load_training_state(copy.deepcopy(a.training_state()))
    for step in range(5, 10):
        assert a.train_step(data, step)["loss"] == b.train_step(data, step)["loss"]


def test_unbounded_scene_and_misses():
    data, info, _ = sphere_scene(n_cams=3, size=12)
    unb = SceneInfo(aabb=info.aabb, unbounded=True, background=info.background, near=0.2, far=50.0)
    model = NeRFModel(SMALL, unb)
    losses = [model.train_step(data, s)["loss"] for s in range(30)]
    assert losses[-1] < losses[0]
    out = model.render(data.cameras[0])
    assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["depth"]).all()
    away = SceneInfo(aabb=torch.tensor([[50.0] * 3, [51.0] * 3]), unbounded=False, background=info.background,
                     near=0.1, far=6.0)
    model = NeRFModel(SMALL, away)
    assert torch.isfinite(torch.tensor(model.train_step(data, 0)["loss"]))
    out = model.render(data.cameras[0])
    torch.testing.assert_close(out["rgb"], info.background.expand(12, 12, 3))
