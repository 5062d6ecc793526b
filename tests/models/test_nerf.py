"""NeRF model: the paper's architecture, hierarchical sampling, learning an analytic sphere scene,
exact resume."""

import copy

import pytest
import torch

from recon.cameras.rays import camera_rays
from recon.fields.encodings import positional_encoding
from recon.models.base import METHODS, SceneInfo
from recon.models.nerf import PRESETS, RAY_BUCKET, NeRFConfig, NeRFMLP, NeRFModel
from recon.models.raymarch import mlp_dtype, ray_bounds
from recon.volrend import scene_to_unit_cube, volume_render
from recon.volrend.occupancy import cell_points
from tests.conftest import train_step, trainer_of
from tests.models.test_ngp import eval_psnr, mean_colour_psnr, sphere_scene

SMALL = NeRFConfig(
    depth=3,
    width=64,
    skip_layer=2,
    pos_bands=4,
    n_coarse=16,
    n_fine=16,
    rays_per_batch=256,
    lr=5e-3,
    lr_final=5e-4,
    lr_decay_steps=150,
    chunk=1024,
    occupancy_res=64,
    occupancy_warmup=64,
)  # the sphere test trains 86 steps with skipping


pytestmark = pytest.mark.usefixtures("one_thread")


def test_paper_preset_is_the_paper_architecture():
    assert METHODS["nerf"].config_cls is NeRFConfig and set(PRESETS) == {"fast", "paper"}
    cfg = NeRFConfig(**PRESETS["paper"])
    assert (cfg.n_coarse, cfg.n_fine, cfg.rays_per_batch, cfg.pos_bands, cfg.dir_bands) == (
        64,
        128,
        4096,
        10,
        4,
    )
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


def test_colour_layer_split_is_the_concatenated_linear():
    """The per-ray direction term of the colour layer equals the paper's per-sample [feature, gamma(d)]
    input to one Linear (its brute-force twin)."""
    torch.manual_seed(0)
    net = NeRFMLP(SMALL)
    R, S = 4, 6
    x, d = torch.randn(R * S, net.pos_dim), torch.randn(R, 27)
    _, rgb = net(x, d)
    _, h = net.geometry(x)
    cat = torch.cat([net.feature(h), d.repeat_interleave(S, 0)], -1)
    torch.testing.assert_close(rgb, torch.sigmoid(net.color(cat)))
    empty_sigma, empty_rgb = net(x[:0], d[:0])  # a chunk in which no ray hits
    assert empty_sigma.shape == (0,) and empty_rgb.shape == (0, 3)


def test_mlp_precision_choice():
    cpu = torch.device("cpu")
    assert mlp_dtype(cpu, "fp32") == torch.float32 and mlp_dtype(cpu, "bf16") == torch.bfloat16
    assert mlp_dtype(cpu, "auto") in (torch.float32, torch.bfloat16)
    with pytest.raises(ValueError, match="precision"):
        mlp_dtype(cpu, "fp8")


def test_bf16_mlp_renders_like_fp32_and_trains():
    """bf16 matmuls (fp32 weights, optimizer and compositing) stay close to the fp32 model and
    give finite fp32 gradients."""
    data, info, _ = sphere_scene(n_cams=2, size=12)
    torch.manual_seed(0)
    exact = NeRFModel(
        NeRFConfig(**{**SMALL.__dict__, "precision": "fp32", "occupancy_res": 0}), info
    )
    half = NeRFModel(
        NeRFConfig(**{**SMALL.__dict__, "precision": "bf16", "occupancy_res": 0}), info
    )
    half.load_state_dict(exact.state_dict())
    a, b = exact.render(data.cameras[0]), half.render(data.cameras[0])
    assert b["rgb"].dtype == torch.float32 and (a["rgb"] - b["rgb"]).abs().max() < 0.03
    stats = train_step(half, data, 0)
    assert torch.isfinite(torch.as_tensor(stats["loss"]))
    grads = [p.grad for p in half.parameters() if p.grad is not None]
    assert grads and all(g.dtype == torch.float32 and torch.isfinite(g).all() for g in grads)


def test_mlps_see_ray_counts_in_buckets_and_padding_changes_nothing():
    """Any number of hit rays reaches the MLPs rounded up to RAY_BUCKET (few matmul shapes for
    oneDNN to compile), and the padded rows change neither the render nor the gradients."""
    data, info, _ = sphere_scene(n_cams=1, size=8)
    model = NeRFModel(NeRFConfig(**{**SMALL.__dict__, "precision": "fp32"}), info)
    seen, forward = [], model.fine.forward
    model.fine.forward = lambda x, d: seen.append((x.shape[0], d.shape[0])) or forward(x, d)
    o, d, _ = camera_rays(data.cameras, 0)
    o, d = o.reshape(-1, 3)[:37], d.reshape(-1, 3)[:37]
    t_min = ray_bounds(info, o, d)[0]
    edges = torch.linspace(0, 1, 9).expand(37, 9) + t_min[:, None]
    t0, t1 = edges[:, :-1], edges[:, 1:]
    out = model._render_net(model.fine, o, d, t0, t1)
    assert seen == [(RAY_BUCKET * 8, RAY_BUCKET)]
    x = o[:, None] + (0.5 * (t0 + t1))[..., None] * d[:, None]
    sigma, rgb = forward(
        model.encode_points(x.reshape(-1, 3)), positional_encoding(d, SMALL.dir_bands)
    )
    twin = volume_render(
        sigma.view(37, 8), rgb.view(37, 8, 3), t0, t1, background=model.background
    ).rgb
    torch.testing.assert_close(out.rgb, twin)
    params = list(model.fine.parameters())
    for g_padded, g_twin in zip(
        torch.autograd.grad(out.rgb.sum(), params),
        torch.autograd.grad(twin.sum(), params),
        strict=True,
    ):
        torch.testing.assert_close(g_padded, g_twin)


def test_learns_sphere_and_renders():
    torch.manual_seed(0)
    data, info, depths = sphere_scene(8, 24)
    model = NeRFModel(SMALL, info)
    baseline = mean_colour_psnr(data.images)
    first = train_step(model, data, 0)
    for step in range(1, 150):
        stats = train_step(model, data, step)
    assert stats["loss"] < 0.2 * first["loss"]
    model.eval()
    out = model.render(data.cameras[0])
    assert (
        out["rgb"].shape == (24, 24, 3)
        and out["depth"].shape == (24, 24)
        and out["acc"].shape == (24, 24)
    )
    assert all(torch.isfinite(v).all() for v in out.values())
    assert eval_psnr(model, data) > baseline + 8
    hit = depths[0] > 0
    assert (out["depth"][hit] - depths[0][hit]).abs().median() < 0.25
    assert out["acc"][hit].mean() > 0.8 and out["acc"][~hit].mean() < 0.15
    # early ray termination (the default render) against evaluating every sample
    model.cfg = NeRFConfig(**{**model.cfg.__dict__, "eps_transmittance": 0.0})
    every = model.render(data.cameras[0])
    for k in ("rgb", "acc"):
        assert (every[k] - out[k]).abs().max() < 1e-3, k


def test_renders_stop_evaluating_rays_behind_an_opaque_slab():
    """Both networks see an opaque slab at t = 2.5 (optical depth 100): samples behind it are
    not evaluated, and the image is the one every sample gives (within the skipped weight)."""
    _, info, _ = sphere_scene(2, 8)
    model = NeRFModel(NeRFConfig(**{**SMALL.__dict__, "occupancy_res": 0}), info)
    evaluated = []

    def slab(x_enc):
        evaluated.append(x_enc.shape[0])
        sigma = 1000.0 * ((x_enc[:, 2].float() + 0.5).abs() < 0.05).float()
        return sigma, torch.ones(x_enc.shape[0], SMALL.width, dtype=x_enc.dtype)

    model.coarse.geometry = model.fine.geometry = slab
    o = torch.tensor([[0.0, 0.0, -3.0], [0.1, 0.0, -3.0]]).repeat(32, 1)
    d = torch.tensor([[0.0, 0.0, 1.0]]).repeat(64, 1)
    outs = {}
    for eps in (0.0, 1e-4):
        model.cfg = NeRFConfig(**{**model.cfg.__dict__, "eps_transmittance": eps})
        evaluated.clear()
        with torch.no_grad():
            outs[eps] = model._render_rays(o, d, jitter=False, terminate=eps > 0)[1]
        outs[eps]["samples"] = sum(evaluated)
    assert outs[1e-4]["samples"] < 0.8 * outs[0.0]["samples"], outs
    assert (outs[0.0]["acc"] > 0.99).all()
    for k in ("rgb", "acc", "depth"):
        assert (outs[1e-4][k] - outs[0.0][k]).abs().max() < 1e-3, k


def test_fine_samples_concentrate_where_coarse_weight_is():
    _, info, _ = sphere_scene(2, 8)
    model = NeRFModel(SMALL, info)
    o = torch.tensor([[0.0, 0.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]])
    # a coarse network whose density is a thin slab at t = 2.5 (z = -0.5): patch its geometry
    model.coarse.geometry = lambda x_enc: (
        30.0 * ((x_enc[:, 2] + 0.5).abs() < 0.05).float(),
        torch.zeros(x_enc.shape[0], SMALL.width),
    )
    model.cfg = NeRFConfig(**{**SMALL.__dict__, "n_coarse": 64, "n_fine": 64})
    seen = {}
    original = model._render_net

    def spy(net, o_, d_, t0, t1, bg=None):
        seen[net is model.fine] = (t0, t1)
        return original(net, o_, d_, t0, t1, bg)

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
        train_step(a, data, step)
    b = NeRFModel(SMALL, info)
    b.load_state_dict(copy.deepcopy(a.state_dict()))
    trainer_of(b).load_state_dict(copy.deepcopy(trainer_of(a).state_dict()))
    for step in range(5, 10):
        assert train_step(a, data, step)["loss"] == train_step(b, data, step)["loss"]


def test_unbounded_scene_and_misses():
    data, info, _ = sphere_scene(n_cams=3, size=12)
    unb = SceneInfo(aabb=info.aabb, unbounded=True, background=info.background, near=0.2, far=50.0)
    model = NeRFModel(SMALL, unb)
    losses = [train_step(model, data, s)["loss"] for s in range(30)]
    assert losses[-1] < losses[0]
    out = model.render(data.cameras[0])
    assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["depth"]).all()
    away = SceneInfo(
        aabb=torch.tensor([[50.0] * 3, [51.0] * 3]),
        unbounded=False,
        background=info.background,
        near=0.1,
        far=6.0,
    )
    model = NeRFModel(SMALL, away)
    assert torch.isfinite(torch.as_tensor(train_step(model, data, 0)["loss"]))
    out = model.render(data.cameras[0])
    torch.testing.assert_close(out["rgb"], info.background.expand(12, 12, 3))


def test_occupancy_shrinks_ranges_to_occupied_cells_and_skips_empty_rays():
    data, info, _ = sphere_scene(n_cams=2, size=16)
    model = NeRFModel(SMALL, info)
    res = model.occupancy.resolution
    centres = cell_points(torch.arange(res**3), res, torch.full((res**3, 3), 0.5))
    # cells whose centre lies within 0.53 (the box is [-1, 1]^3, cell half-diagonal 0.027) cover the
    # radius-0.5 ball and reach no further than 0.56
    model.occupancy.occupied.copy_((2 * centres - 1).norm(dim=-1) < 0.53)
    o, d, _ = camera_rays(data.cameras, 0)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    t_min, t_max = model._ray_range(o, d, jitter=False)
    b = (o * d).sum(-1)
    disc = b**2 - ((o * o).sum(-1) - 0.5**2)
    enter, exit_ = -b - disc.clamp_min(0).sqrt(), -b + disc.clamp_min(0).sqrt()
    inner = disc > 0.05  # clearly through the radius-0.5 ball: its whole chord lies in the range
    assert (
        inner.sum() > 20
        and (t_min[inner] <= enter[inner]).all()
        and (t_max[inner] >= exit_[inner]).all()
    )
    far_off = b**2 - ((o * o).sum(-1) - 0.6**2) < 0  # misses the ball grown by 3 cells: no range
    assert far_off.sum() > 20 and (t_max[far_off] == t_min[far_off]).all()
    box_min, box_max = ray_bounds(info, o, d)
    assert (t_min >= box_min).all() and (t_max <= box_max).all()
    seen = []
    original = model._render_terminated  # a render's passes (early ray termination)
    model._render_terminated = lambda net, *a, **k: (
        seen.append(a[0].shape[0]) or original(net, *a, **k)
    )
    out = model.render(data.cameras[0])
    assert seen and sum(seen) == 2 * int((t_max > t_min).sum())  # coarse + fine, hit rays only
    torch.testing.assert_close(
        out["rgb"].reshape(-1, 3)[far_off], info.background.expand(int(far_off.sum()), 3)
    )
    assert (out["acc"].reshape(-1)[far_off] == 0).all()


def test_a_model_saved_without_occupancy_grid_loads_and_renders_the_same():
    data, info, _ = sphere_scene(n_cams=2, size=8)
    old = NeRFModel(NeRFConfig(**{**SMALL.__dict__, "occupancy_res": 0}), info)
    new = NeRFModel(SMALL, info)
    new.load_state_dict(old.state_dict())
    assert new.occupancy is None
    torch.testing.assert_close(
        new.render(data.cameras[0])["rgb"], old.render(data.cameras[0])["rgb"]
    )


def test_unbounded_scene_seeds_from_points_and_missed_rays_see_the_learned_background():
    from tests.models.test_ngp import unbounded_sphere_scene

    data, info = unbounded_sphere_scene(n_cams=3, size=12)
    model = NeRFModel(SMALL, info)
    grid = model.occupancy
    unit = scene_to_unit_cube(info.points, info.aabb, True)
    assert grid.is_occupied(unit).all() and 0 < grid.occupancy_fraction() < 0.1
    assert model.environment is not None  # auto: learned for an unbounded scene
    losses = [train_step(model, data, s)["loss"] for s in range(20)]
    assert losses[-1] < losses[0] and model.environment.net[2].weight.grad is not None
    # rays that cross no occupied cell get the environment map, with its gradient
    grid.occupied.fill_(False)
    o, d, _ = camera_rays(data.cameras, 0)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    _, fine = model._render_rays(o, d, jitter=False)
    assert not fine["hit"].any() and (fine["acc"] == 0).all()
    torch.testing.assert_close(fine["rgb"], model.environment(d))
    trainer_of(model).optimizers["main"].zero_grad(set_to_none=True)
    fine["rgb"].sum().backward()
    assert model.environment.net[0].weight.grad.abs().sum() > 0
    scene_bg = NeRFModel(NeRFConfig(**{**SMALL.__dict__, "background": "scene"}), info)
    assert scene_bg.environment is None
    no_points = NeRFModel(SMALL, SceneInfo(**{**info.__dict__, "points": None}))
    assert no_points.occupancy.occupied.all()  # as before: every cell until warm-up ends
