"""Instant-NGP model: learns an analytic sphere scene in seconds, renders finite images of the
right shape, and resumes exactly from state_dict + training_state."""

import copy
import math

import pytest
import torch

from recon.cameras import Cameras
from recon.cameras.cameras import intrinsics_matrix
from recon.cameras.look_at import look_at
from recon.cameras.rays import camera_rays
from recon.models.base import METHODS, SceneInfo, TrainData
from recon.models.ngp import PRESETS, NGPConfig, NGPModel, uses_distortion
from tests.conftest import train_step, trainer_of

RADIUS = 0.5


def look_at_origin(eye: torch.Tensor) -> torch.Tensor:
    """OpenCV cam_from_world of a camera at eye looking at the origin, world z up."""
    return look_at(eye, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))


def ring_cameras(n: int, size: int, radius: float = 2.5, elevation: float = 0.4) -> Cameras:
    eyes = [
        radius
        * torch.tensor(
            [
                math.cos(elevation) * math.cos(a),
                math.cos(elevation) * math.sin(a),
                math.sin(elevation) * (1 if i % 2 else -1),
            ]
        )
        for i, a in enumerate(torch.arange(n) * 2 * math.pi / n)
    ]
    f = torch.full((n,), 1.2 * size)
    K = intrinsics_matrix(f, f, torch.full((n,), size / 2), torch.full((n,), size / 2))
    wh = torch.full((n,), size, dtype=torch.int64)
    return Cameras(K, torch.stack([look_at_origin(e) for e in eyes]), wh, wh)


def sphere_images(cameras: Cameras, background: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact renders of an opaque sphere (colour 0.5 + 0.5 n) -> images (C, H, W, 3), z-depth."""
    imgs, depths = [], []
    for i in range(len(cameras)):
        o, d, z_per_t = camera_rays(cameras, i)
        b = (o * d).sum(-1)
        disc = b**2 - ((o * o).sum(-1) - RADIUS**2)
        t = -b - disc.clamp_min(0).sqrt()
        hit = (disc > 0) & (t > 0)
        n = (o + t[..., None] * d) / RADIUS
        imgs.append(torch.where(hit[..., None], 0.5 + 0.5 * n, background))
        depths.append(torch.where(hit, t * z_per_t, torch.zeros_like(t)))
    return torch.stack(imgs).float(), torch.stack(depths)


def sphere_scene(n_cams: int = 8, size: int = 32):
    bg = torch.tensor([1.0, 1.0, 1.0])
    cams = ring_cameras(n_cams, size)
    imgs, depths = sphere_images(cams, bg)
    info = SceneInfo(
        aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]),
        unbounded=False,
        background=bg,
        near=0.1,
        far=6.0,
    )
    return TrainData(imgs, cams), info, depths


def mean_colour_psnr(images: torch.Tensor) -> float:
    mse = ((images - images.reshape(-1, 3).mean(0)) ** 2).mean().item()
    return -10 * math.log10(mse)


def eval_psnr(model, data: TrainData) -> float:
    mses = [
        ((model.render(data.cameras[i])["rgb"] - data.images[i]) ** 2).mean().item()
        for i in range(len(data))
    ]
    return -10 * math.log10(sum(mses) / len(mses))


SMALL = NGPConfig(
    log2_table_size=14,
    n_max=128,
    n_levels=8,
    rays_per_batch=256,
    samples_per_batch=0,
    march_steps=96,
    occupancy_res=32,
    occupancy_warmup=16,
    occupancy_decay=0.6,
    lr_decay_steps=150,
    chunk=2048,
)


pytestmark = pytest.mark.usefixtures("one_thread")


def test_registered_with_presets():
    spec = METHODS["ngp"]
    assert spec.config_cls is NGPConfig and set(PRESETS) == {"fast", "paper"}
    paper = NGPConfig(**PRESETS["paper"])
    assert (paper.n_levels, paper.n_features, paper.log2_table_size, paper.n_min, paper.n_max) == (
        16,
        2,
        19,
        16,
        2048,
    )


def test_learns_sphere_and_renders():
    torch.manual_seed(0)
    data, info, depths = sphere_scene(8, 24)
    model = NGPModel(SMALL, info)
    baseline = mean_colour_psnr(data.images)
    first = train_step(model, data, 0)
    for step in range(1, 150):
        stats = train_step(model, data, step)
    assert stats["loss"] < 0.2 * first["loss"]
    # the occupancy grid has pruned empty space, and marching now takes far fewer samples
    assert 0 < stats["occupied"] < 0.4 and stats["samples_per_ray"] < 0.5 * first["samples_per_ray"]
    model.eval()
    out = model.render(data.cameras[0])
    assert (
        out["rgb"].shape == (24, 24, 3)
        and out["depth"].shape == (24, 24)
        and out["acc"].shape == (24, 24)
    )
    assert all(torch.isfinite(v).all() for v in out.values())
    test_psnr = eval_psnr(model, data)
    assert test_psnr > baseline + 8, (test_psnr, baseline)
    # depth: on pixels that see the sphere, the rendered z-depth is near the exact one
    hit = depths[0] > 0
    assert (out["depth"][hit] - depths[0][hit]).abs().median() < 0.25
    assert out["acc"][hit].mean() > 0.8 and out["acc"][~hit].mean() < 0.15
    sigma_in, sigma_out = model.density(torch.tensor([[0.0, 0.0, 0.0], [0.9, 0.9, 0.9]]))
    assert sigma_in > sigma_out


def test_resume_is_exact():
    data, info, _ = sphere_scene(n_cams=4, size=16)
    cfg = NGPConfig(**{**SMALL.__dict__, "samples_per_batch": 3000})  # the ray batch adapts
    a = NGPModel(cfg, info)
    for step in range(20):
        train_step(a, data, step)
    b = NGPModel(cfg, info)
    b.load_state_dict(copy.deepcopy(a.state_dict()))
    trainer_of(b).load_state_dict(copy.deepcopy(trainer_of(a).state_dict()))
    for step in range(20, 36):  # crosses an occupancy update (step 32), after warm-up
        la, lb = train_step(a, data, step), train_step(b, data, step)
        assert la["loss"] == lb["loss"]
    for (na, pa), (_, pb) in zip(a.state_dict().items(), b.state_dict().items()):
        assert torch.equal(pa, pb), na
    assert a.n_rays == b.n_rays != cfg.rays_per_batch


def test_misses_and_empty_batches_are_safe():
    data, info, _ = sphere_scene(n_cams=2, size=8)
    # rays that all miss the box: put the box far away
    far_info = SceneInfo(
        aabb=torch.tensor([[50.0] * 3, [51.0] * 3]),
        unbounded=False,
        background=info.background,
        near=0.1,
        far=6.0,
    )
    model = NGPModel(SMALL, far_info)
    stats = train_step(model, data, 0)
    assert math.isfinite(stats["loss"]) and stats["samples_per_ray"] == 0
    out = model.render(data.cameras[0])
    torch.testing.assert_close(out["rgb"], info.background.expand(8, 8, 3))
    assert (out["acc"] == 0).all() and (out["depth"] == 0).all()


def test_unbounded_scene_trains():
    data, info, _ = sphere_scene(n_cams=4, size=16)
    info = SceneInfo(aabb=info.aabb, unbounded=True, background=info.background, near=0.1, far=20.0)
    # cone_angle 1/32: steps grow from t = step / cone ~ 1.2 on, ~120 samples out to t = 20
    model = NGPModel(NGPConfig(**{**SMALL.__dict__, "cone_angle": 1 / 32}), info)
    losses = [train_step(model, data, s)["loss"] for s in range(25)]
    assert losses[-1] < losses[0]
    out = model.render(data.cameras[1])
    assert torch.isfinite(out["rgb"]).all() and out["rgb"].shape == (16, 16, 3)


def test_trunc_exp_value_and_clamped_gradient():
    from recon.models.raymarch import trunc_exp

    x = torch.tensor([-3.0, 0.0, 2.0, 20.0, 100.0], dtype=torch.float64, requires_grad=True)
    y = trunc_exp(x)
    torch.testing.assert_close(y[:4], torch.exp(x[:4]))
    y.sum().backward()
    expected = torch.exp(torch.tensor([-3.0, 0.0, 2.0, 15.0, 15.0], dtype=torch.float64))
    torch.testing.assert_close(x.grad, expected)  # d/dx exp(x) below 15, exp(15) above
    assert torch.autograd.gradcheck(
        trunc_exp, (torch.tensor([-1.0, 0.5, 3.0], dtype=torch.float64, requires_grad=True),)
    )


def sky(directions: torch.Tensor) -> torch.Tensor:
    """A smooth colour per direction: what a real capture shows behind its scene."""
    return 0.5 + 0.4 * directions


def unbounded_sphere_scene(n_cams: int = 6, size: int = 16, n_points: int = 300):
    """The sphere in front of a direction-dependent 'sky', as an unbounded scene with SfM-like
    points on its surface."""
    cams = ring_cameras(n_cams, size)
    imgs, _ = sphere_images(cams, torch.zeros(3))
    for i in range(n_cams):
        _, d, _ = camera_rays(cams, i)
        miss = (imgs[i] == 0).all(-1)
        imgs[i][miss] = sky(d[miss]).float()
    pts = torch.nn.functional.normalize(
        torch.randn(n_points, 3, generator=torch.Generator().manual_seed(0)), dim=-1
    )
    info = SceneInfo(
        aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]),
        unbounded=True,
        background=torch.ones(3),
        near=0.1,
        far=100.0,
        points=RADIUS * pts,
    )
    return TrainData(imgs, cams), info


def test_unbounded_first_step_is_capped_and_seeded_from_points():
    data, info = unbounded_sphere_scene()
    cfg = NGPConfig(
        **{
            **SMALL.__dict__,
            "max_samples_per_ray": 40,
            "cone_angle": 1 / 64,
            "occupancy_seed_dilation": 1,
        }
    )
    model = NGPModel(cfg, info)
    grid = model.occupancy
    assert grid.is_occupied(model.to_unit(info.points)).all()  # every point's cell
    assert 0 < grid.occupancy_fraction() < 0.1  # and a thin shell around them, not the whole cube
    assert not grid.is_occupied(
        model.to_unit(torch.tensor([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]]))
    ).any()
    # points outside the box (the sparse far tail) seed nothing: one far cell spans a vast region
    far = torch.tensor([[40.0, 0.0, 0.0], [0.0, -9.0, 3.0]])
    with_far = NGPModel(
        cfg, SceneInfo(**{**info.__dict__, "points": torch.cat([info.points, far])})
    )
    assert torch.equal(with_far.occupancy.occupied, grid.occupied)
    stats = train_step(model, data, 0)
    assert 0 < stats["samples_per_ray"] <= 40
    unseeded = NGPModel(cfg, SceneInfo(**{**info.__dict__, "points": None}))
    assert unseeded.occupancy.occupied.all()  # no points: every cell, as before
    assert train_step(unseeded, data, 0)["samples_per_ray"] == 40  # ~150 steps to t = 100, capped
    # uncapped, every cell occupied: the whole ray, its far part linear in disparity (~150 steps),
    # not ~64 ln(100 / 2.3) ~ 240 more cone steps
    from recon.volrend.occupancy import _warp

    free = NGPModel(NGPConfig(**{**cfg.__dict__, "max_samples_per_ray": 0}), unseeded.scene)
    t = torch.tensor([info.near, info.far])
    s = _warp(t, free.step_size, cfg.cone_angle, free.disparity_from)
    rays = data.rays()
    n = torch.bincount(free._occupied_samples(rays["origins"], rays["directions"], jitter=False)[0])
    assert (n == math.ceil(s[1] - s[0])).all() and n[0] < 160


@pytest.mark.slow
def test_learned_background_fills_what_the_volume_leaves_open():
    torch.manual_seed(0)
    data, info = unbounded_sphere_scene()
    model = NGPModel(NGPConfig(**{**SMALL.__dict__, "cone_angle": 1 / 64}), info)
    assert model.environment is not None  # auto: learned for an unbounded scene
    for step in range(120):
        train_step(model, data, step)
    model.eval()
    out = model.render(data.cameras[0])
    _, d, _ = camera_rays(data.cameras, 0)
    sky_px = (data.images[0] - sky(d)).abs().max(-1).values < 1e-6
    assert sky_px.sum() > 30
    err = (out["rgb"][sky_px] - data.images[0][sky_px]).abs().mean()
    white = (info.background - data.images[0][sky_px]).abs().mean()
    assert err < 0.25 * white, (err, white)  # the sky is learned, not the fixed white
    # a ray that crosses only empty cells sees exactly the environment map
    model.occupancy.occupied.fill_(False)
    empty = model.render(data.cameras[0])
    assert (empty["acc"] == 0).all()
    torch.testing.assert_close(empty["rgb"], model.environment(d.reshape(-1, 3)).reshape(d.shape))
    fixed = NGPModel(NGPConfig(**{**SMALL.__dict__, "background": "scene"}), info)
    assert fixed.environment is None
    bounded = NGPModel(SMALL, sphere_scene(2, 8)[1])
    assert bounded.environment is None
    with pytest.raises(ValueError, match="background"):
        NGPModel(NGPConfig(**{**SMALL.__dict__, "background": "sky"}), info)


def test_a_run_saved_without_learned_background_loads_with_the_scene_colour():
    data, info = unbounded_sphere_scene(n_cams=2, size=8)
    old = NGPModel(NGPConfig(**{**SMALL.__dict__, "background": "scene"}), info)
    new = NGPModel(SMALL, info)
    new.load_state_dict(old.state_dict())
    assert new.environment is None
    torch.testing.assert_close(
        new.render(data.cameras[0])["rgb"], old.render(data.cameras[0])["rgb"]
    )


def test_both_training_passes_match_the_prepass_twin_on_outputs_and_gradients():
    """Training renders either from one density pass with gradients (termination decided on its
    values) or, once termination drops many samples, from a density pre-pass without gradients
    and the field on the survivors; the literal twin evaluates the density without gradients
    first and the field again on the survivors. All three: the same samples, loss, gradients."""
    from recon.models.ngp import PREPASS_BELOW_KEPT
    from recon.volrend import terminated_mask, volume_render

    data, info = unbounded_sphere_scene(n_cams=2, size=16)
    info = SceneInfo(**{**info.__dict__, "points": None})  # every cell occupied: long rays
    model = NGPModel(NGPConfig(**{**SMALL.__dict__, "cone_angle": 1 / 64}), info)
    with torch.no_grad():
        model.field.density_mlp[-1].bias[0] = 2.0  # sigma ~ e^2 everywhere: rays terminate early
    rays = data.rays()
    o, d, target = rays["origins"][::3], rays["directions"][::3], rays["rgb"][::3]
    state = model.generator.get_state()

    def loss_and_grads(render):
        model.zero_grad(set_to_none=True)
        model.generator.set_state(state)  # the same jittered samples
        out, ri, *_ = render()
        n = ri.numel()
        loss = ((out.rgb - target) ** 2).mean()
        loss.backward()
        return loss.detach(), n, [p.grad.clone() for p in model.parameters() if p.grad is not None]

    def prepass():
        ri, t0, t1, x = model._occupied_samples(o, d, jitter=True)
        with torch.no_grad():
            keep = terminated_mask(model.field.sigma(x), t0, t1, ri, model.cfg.eps_transmittance)
        ri, t0, t1, x = ri[keep], t0[keep], t1[keep], x[keep]
        sigma, geo = model.field.geometry(x)
        rgb = model.field.color(geo, model.field.encode_directions(d)[ri])
        return volume_render(sigma, rgb, t0, t1, ri, o.shape[0], model.background_colour(d)), ri

    assert model._kept_fraction == 1.0  # a new run starts with the single pass
    one_pass = loss_and_grads(lambda: model._render_rays_train(o, d))
    assert model._kept_fraction < PREPASS_BELOW_KEPT  # so the next step takes the pre-pass
    two_pass = loss_and_grads(lambda: model._render_rays_train(o, d))
    twin = loss_and_grads(prepass)
    marched = model._occupied_samples(o, d, jitter=True)[0].numel()
    assert one_pass[1] == two_pass[1] == twin[1] < 0.7 * marched  # the same samples dropped
    for fast in (one_pass, two_pass):
        torch.testing.assert_close(fast[0], twin[0])
        assert len(fast[2]) == len(twin[2]) > 0
        for gf, gs in zip(fast[2], twin[2]):
            torch.testing.assert_close(gf, gs, rtol=1e-4, atol=1e-7)


def test_distortion_is_on_by_default_for_unbounded_scenes_only():
    assert uses_distortion("auto", True) and not uses_distortion("auto", False)
    assert uses_distortion("on", False) and not uses_distortion("off", True)
    with pytest.raises(ValueError, match="distortion must be"):
        uses_distortion("yes", True)


def test_distortion_loss_is_added_on_the_normalized_marching_distance():
    data, info = unbounded_sphere_scene(n_cams=2, size=12)
    model = NGPModel(
        NGPConfig(**{**SMALL.__dict__, "cone_angle": 1 / 64, "distortion_weight": 0.1}), info
    )
    t = torch.tensor([info.near, 1.0, 3.0, 30.0, info.far])
    s = model.normalized_distance(t)
    torch.testing.assert_close(s[[0, -1]], torch.tensor([0.0, 1.0]))
    assert (s.diff() > 0).all()
    stats = train_step(model, data, 0)
    mse = 10 ** (-stats["psnr"] / 10)
    assert stats["loss"] > mse * (1 + 1e-4)  # the distortion term is part of the loss
    plain = train_step(
        NGPModel(NGPConfig(**{**SMALL.__dict__, "cone_angle": 1 / 64, "distortion": "off"}), info),
        data,
        0,
    )
    torch.testing.assert_close(float(plain["loss"]), 10 ** (-float(plain["psnr"]) / 10))
