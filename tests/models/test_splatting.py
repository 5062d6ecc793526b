"""The 3dgs Model: initialisation, a short fit of a tiny synthetic scene, densification with
consistent optimizer state, exact resume across a count change, rendering and registration."""

import io
import math

import numpy as np
import pytest
import torch

from recon.cameras import Cameras
from recon.cameras.look_at import look_at
from recon.fields.sh import C0
from recon.gaussians.render import composite_rgb, mean_compensation, project_splats
from recon.models.base import METHODS, SceneInfo, TrainData
from recon.models.splatting import GaussianModel
from recon.models.splatting_config import PRESETS, GaussiansConfig
from recon.options import field_help
from tests.conftest import train_step, trainer_of


def look_at_origin(eye):
    """OpenCV cam_from_world looking at the origin with world z up."""
    eye = torch.tensor(eye, dtype=torch.float64)
    return look_at(eye, torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0]))


def ring(n=8, size=32, radius=3.0):
    cfw = torch.stack(
        [
            look_at_origin(
                (
                    radius * math.cos(2 * math.pi * i / n),
                    radius * math.sin(2 * math.pi * i / n),
                    0.7 * math.sin(i),
                )
            )
            for i in range(n)
        ]
    )
    K = (
        torch.tensor(
            [[1.2 * size, 0, size / 2], [0, 1.2 * size, size / 2], [0, 0, 1]], dtype=torch.float64
        )
        .expand(n, 3, 3)
        .clone()
    )
    wh = torch.full((n,), size)
    return Cameras(K, cfw, wh, wh.clone())


def synthetic_scene(size=32):
    """Six opaque coloured Gaussians seen by 8 ring cameras, rendered by our renderer."""
    gen = torch.Generator().manual_seed(0)
    truth = {
        "means": torch.randn(6, 3, generator=gen) * 0.4,
        "quats": torch.randn(6, 4, generator=gen),
        "log_scales": torch.log(torch.rand(6, 3, generator=gen) * 0.3 + 0.1),
        "opacity_logits": torch.full((6,), 3.0),
        "sh_dc": (torch.rand(6, 1, 3, generator=gen) - 0.5) / C0,
        "sh_rest": torch.zeros(6, 0, 3),
    }
    cams = ring(size=size)
    with torch.no_grad():
        images = torch.stack(
            [
                composite_rgb(project_splats(truth, cams[i], 0), torch.zeros(3))[0]
                for i in range(len(cams))
            ]
        ).clamp(0, 1)
    scene = SceneInfo(
        aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]]),
        unbounded=False,
        background=torch.zeros(3),
        near=0.1,
        far=6.0,
    )
    return scene, TrainData(images, cams)


def config(**overrides):
    base = {
        **PRESETS["fast"],
        "init": "random",
        "init_points": 300,
        "init_from_images": False,
        "densify_start": 20,
        "densify_interval": 20,
        "densify_grad_threshold": 0.00005,
        "sh_degree_interval": 30,
    }
    return GaussiansConfig(**{**base, **overrides})


def test_training_fits_a_tiny_scene_and_densifies():
    scene, data = synthetic_scene()
    baseline = -10 * math.log10(((data.images - data.images.mean((0, 1, 2))) ** 2).mean().item())
    model = GaussianModel(config(), scene)
    losses, counts = [], []
    for step in range(160):
        stats = train_step(model, data, step)
        losses.append(stats["loss"])
        counts.append(stats["num_gaussians"])
        for group in (
            trainer_of(model).optimizers["main"].param_groups
        ):  # moments always shaped like their tensor
            p = group["params"][0]
            assert p is model.params[group["name"]]
            if p in trainer_of(model).optimizers["main"].state:
                assert trainer_of(model).optimizers["main"].state[p]["exp_avg"].shape == p.shape
    assert np.mean(losses[-16:]) < 0.5 * np.mean(losses[:16])
    psnr = np.mean(
        [
            -10
            * math.log10(
                ((model.render(data.cameras[i])["rgb"] - data.images[i]) ** 2).mean().item()
            )
            for i in range(len(data))
        ]
    )
    assert psnr > baseline + 7, (psnr, baseline)
    assert len(set(counts)) > 1  # densification changed the count
    assert int(model.active_sh_degree) == 3


def straight_and_resumed(cfg, scene, data, saved_at: int, steps: int):
    """(a model trained `steps` steps straight, one saved after `saved_at` steps through
    state_dict / training_state and trained on to `steps`, the saved model); asserts the two
    runs end with the same Gaussians bit for bit."""
    straight = GaussianModel(cfg, scene)
    for step in range(steps):
        train_step(straight, data, step)
    first = GaussianModel(cfg, scene)
    for step in range(saved_at):
        train_step(first, data, step)
    buffer = io.BytesIO()
    torch.save({"model": first.state_dict(), "training": trainer_of(first).state_dict()}, buffer)
    buffer.seek(0)
    saved = torch.load(buffer, weights_only=True)
    resumed = GaussianModel(cfg, scene)
    resumed.load_state_dict(saved["model"])
    trainer_of(resumed).load_state_dict(saved["training"])
    assert resumed.num_gaussians == first.num_gaussians
    for step in range(saved_at, steps):
        train_step(resumed, data, step)
    for name in straight.params:
        assert torch.equal(straight.params[name], resumed.params[name]), name
    return straight, resumed, first


def test_resume_is_exact_across_densification():
    scene, data = synthetic_scene(size=24)
    cfg = config(densify_start=5, densify_interval=10)  # densifies at steps 10, 20, 30, 40
    _, _, first = straight_and_resumed(cfg, scene, data, saved_at=25, steps=40)
    assert first.num_gaussians != 300


def test_image_init_replaces_the_random_start_at_step_0():
    scene, data = synthetic_scene()
    model = GaussianModel(config(init_from_images=True), scene)
    random_means = model.params["means"].detach().clone()
    train_step(model, data, 0)
    assert model.num_gaussians <= 300 and not torch.equal(
        model.params["means"][:5], random_means[:5]
    )
    for group in (
        trainer_of(model).optimizers["main"].param_groups
    ):  # the optimizer follows the new tensors
        assert group["params"][0] is model.params[group["name"]]


def test_render_outputs_and_normalized_depth():
    scene, data = synthetic_scene()
    model = GaussianModel(config(), scene)
    out = model.render(data.cameras[0])
    assert out["rgb"].shape == (32, 32, 3) and out["depth"].shape == (32, 32)
    hit = out["acc"] > 0.05
    assert hit.any()
    centre_distance = 3.0  # camera ring radius; the random init fills [-1, 1]^3
    assert (
        (out["depth"][hit] > centre_distance - 2.0) & (out["depth"][hit] < centre_distance + 2.0)
    ).all()
    assert (out["depth"][out["acc"] == 0] == 0).all()


def test_registered_with_flat_documented_config():
    import dataclasses

    spec = METHODS["3dgs"]
    assert spec.config_cls is GaussiansConfig and set(spec.presets) == {"fast", "paper", "gpu"}
    helps = field_help(GaussiansConfig)
    assert {f.name for f in dataclasses.fields(GaussiansConfig)} == set(helps)
    for preset in spec.presets.values():
        GaussiansConfig(**preset)


def test_the_paper_preset_scales_the_reference_schedule_to_the_planned_run():
    """schedule_fit reference (the paper preset, a CUDA run's default): INRIA's 30,000-step
    proportions kept in a shorter plan; the fast preset ends each at its tuned share; a plan
    as long as the reference keeps it; a re-plan refits with the same proportions."""
    from recon.models.splatting_config import SCHEDULE_FRACTIONS, schedule_fractions

    paper = GaussiansConfig(**{**PRESETS["paper"], "schedule_steps": 12_000})
    fractions = schedule_fractions(paper)
    assert fractions == pytest.approx(
        {
            "lr_decay_steps": 1.0,
            "densify_stop": 0.5,
            "opacity_reset_interval": 0.1,
            "sh_degree_interval": 1 / 30,
            "relocate_stop": 25 / 30,
        }
    )
    assert schedule_fractions(GaussiansConfig(**PRESETS["fast"])) is SCHEDULE_FRACTIONS
    scene, _ = synthetic_scene()
    model = GaussianModel(paper, scene)
    c = model.config
    assert (
        c.lr_decay_steps,
        c.densify_stop,
        c.opacity_reset_interval,
        c.sh_degree_interval,
        c.relocate_stop,
    ) == (12_000, 6_000, 1_200, 400, 10_000)
    assert model.strategy.stop == 6_000
    assert model.replan(6_000, 100) == 6_000 and model.strategy.stop == 3_000
    full = GaussiansConfig(**{**PRESETS["paper"], "schedule_steps": 30_000})
    assert GaussianModel(full, scene).config == full
    with pytest.raises(ValueError, match="schedule_fit"):
        GaussianModel(GaussiansConfig(schedule_fit="other"), scene)


def test_scene_lrs_anneal_in_the_second_half_of_the_decay():
    """scene_lrs' worked example (lr_opacity 0.05, anneal 0.1 over 1,000 steps: 0.05 at 500,
    0.05 * 0.1^0.5 = 0.0158 at 750, 0.005 from 1,000 on), every group alike; lr_anneal 1 keeps
    the reference's constant rates and auto (-1) anneals unbounded captures only; a training
    step sets the rates in the optimizer."""
    from recon.models.splatting_rules import SCENE_RATES, anneal_factor, scene_lrs

    c = GaussiansConfig(lr_opacity=0.05, lr_decay_steps=1000)
    assert scene_lrs(c, 0, 0.1)["opacity_logits"] == scene_lrs(c, 500, 0.1)["opacity_logits"]
    assert scene_lrs(c, 500, 0.1)["opacity_logits"] == 0.05
    assert scene_lrs(c, 750, 0.1)["opacity_logits"] == pytest.approx(0.0158114, rel=1e-5)
    assert scene_lrs(c, 1000, 0.1)["opacity_logits"] == pytest.approx(0.005)
    assert scene_lrs(c, 4000, 0.1)["opacity_logits"] == pytest.approx(0.005)
    for group, field in SCENE_RATES.items():
        assert scene_lrs(c, 1000, 0.1)[group] == pytest.approx(0.1 * getattr(c, field))
        assert scene_lrs(c, 10**6, 1.0)[group] == getattr(c, field)
    fast = GaussiansConfig(**PRESETS["fast"])
    assert (anneal_factor(fast, True), anneal_factor(fast, False)) == (0.1, 1.0)
    assert anneal_factor(GaussiansConfig(), True) == 1.0  # the paper preset: constant rates
    assert anneal_factor(GaussiansConfig(lr_anneal=0.3), False) == 0.3
    with pytest.raises(ValueError, match="lr_anneal"):
        GaussianModel(config(lr_anneal=0.0), synthetic_scene()[0])

    scene, data = synthetic_scene()  # bounded: auto keeps the rates constant
    model = GaussianModel(config(lr_decay_steps=10), scene)
    assert model.anneal == 1.0
    model = GaussianModel(config(lr_anneal=0.1, lr_decay_steps=10), scene)
    for step in range(8):
        train_step(model, data, step)
    lrs = {g["name"]: g["lr"] for g in trainer_of(model).optimizers["main"].param_groups}
    for group, lr in scene_lrs(model.config, 7, 0.1).items():
        assert lrs[group] == pytest.approx(lr) and lr < getattr(model.config, SCENE_RATES[group])


def test_replan_shortens_the_schedules_and_the_densification_that_follows_them():
    """A run re-planned from 1,600 to 1,000 steps at step 500: lr decay and densification end
    earlier (the strategy follows); longer estimates lengthen them back, never past the plan;
    an end that would be past comes at the next step."""
    scene, _ = synthetic_scene()
    model = GaussianModel(GaussiansConfig(**{**PRESETS["fast"], "schedule_steps": 1600}), scene)
    assert (model.config.lr_decay_steps, model.strategy.stop) == (1600, 1120)
    assert model.replan(1000, 500) == 1000
    assert (model.config.lr_decay_steps, model.config.densify_stop) == (1000, 700)
    assert model.strategy.stop == 700 and model.config.schedule_steps == 1000
    assert model.replan(1000, 550) == 0  # the same estimate: nothing changes
    assert model.replan(800, 550) == 800 and model.strategy.stop == 560
    # a longer estimate lengthens back what has not ended, never beyond the plan
    assert model.replan(1200, 555) == 1200 and model.strategy.stop == 840
    assert model.replan(5000, 600) == 1600 and model.strategy.stop == 1120
    # densification over: a shorter estimate moves the lr decay only
    assert model.replan(1300, 1200) == 1300 and model.strategy.stop == 1120
    assert model.config.lr_decay_steps == 1300
    # re-planned shorter than what is past: the densification's last step comes at once
    fresh = GaussianModel(GaussiansConfig(**{**PRESETS["fast"], "schedule_steps": 1600}), scene)
    assert fresh.replan(800, 650) == 800 and fresh.strategy.stop == 651
    # a checkpoint keeps the schedules as re-planned (clamps and ended ones included): resume
    resumed = GaussianModel(GaussiansConfig(**{**PRESETS["fast"], "schedule_steps": 1600}), scene)
    trainer_of(resumed).load_state_dict(trainer_of(fresh).state_dict())
    assert resumed.config == fresh.config and resumed.strategy == fresh.strategy


def test_coarse_to_fine_fits_downscaled_targets_first():
    scene, data = synthetic_scene(size=256)
    model = GaussianModel(config(c2f_factor=4, c2f_interval=3), scene)
    sizes = []
    for step in range(8):
        train_step(model, data, step)
        sizes.append(sorted(data._levels))
    assert (
        sizes[0] == [4] and sizes[3] == [2, 4] and sizes[7] == [2, 4]
    )  # 1/4, 1/4, 1/4, 1/2, ..., full
    assert data.downsampled(4).images.shape[1:3] == (64, 64)
    out = model.render(data.cameras[0])  # renders at whatever size it is asked
    assert out["rgb"].shape == (256, 256, 3)


def test_appearance_learns_per_image_exposure_and_renders_with_the_nearest_corrections():
    """Training images whose exposure alternates by +-15 %: with appearance on, the corrections
    take the difference (renders of the training cameras, which get their own correction, fit
    better than without), and a novel camera gets its neighbours' corrections; the corrections
    and camera anchors survive a save/load."""
    from recon.models.appearance import centred_corrections, neighbour_correction

    scene, data = synthetic_scene()
    gains = torch.tensor([1.15 if i % 2 else 0.85 for i in range(len(data))])
    exposed = TrainData((data.images * gains[:, None, None, None]).clamp(0, 1), data.cameras)
    fits = {}
    for mode in ("off", "on"):
        torch.manual_seed(0)
        model = GaussianModel(config(appearance=mode, lr_appearance=0.005), scene)
        for step in range(200):
            train_step(model, exposed, step)
        fits[mode] = model
    on = fits["on"]
    assert (
        on.stats()["appearance_max_gain_dev"] > 0.05
        and "appearance_max_gain_dev" not in fits["off"].stats()
    )
    err = {
        m: np.mean(
            [
                float((fits[m].render(exposed.cameras[i])["rgb"] - exposed.images[i]).abs().mean())
                for i in range(len(data))
            ]
        )
        for m in fits
    }
    assert err["on"] < err["off"]
    novel = ring(n=16)[3]  # between training cameras 1 and 2
    corr = centred_corrections(on.appearance.deltas.detach())
    wfc = novel.world_from_cam[0].float()
    expected = neighbour_correction(
        corr, on.appearance.centers, on.appearance.directions, wfc[:3, 3], wfc[:3, 2]
    )
    plain = composite_rgb(
        project_splats(on.gaussians(), novel.to(dtype=torch.float32), 3), on.background
    )[0]
    assert torch.allclose(
        on.render(novel.to(dtype=torch.float32))["rgb"],
        plain @ expected[:, :3].T + expected[:, 3],
        atol=1e-5,
    )
    buffer = io.BytesIO()
    torch.save({"model": on.state_dict(), "training": trainer_of(on).state_dict()}, buffer)
    buffer.seek(0)
    saved = torch.load(buffer, weights_only=True)
    again = GaussianModel(config(appearance="on", lr_appearance=0.005), scene)
    again.load_state_dict(saved["model"])
    trainer_of(again).load_state_dict(saved["training"])
    assert torch.equal(again.appearance.deltas, on.appearance.deltas)
    assert torch.equal(again.appearance.centers, on.appearance.centers)
    assert torch.equal(again.render(data.cameras[1])["rgb"], on.render(data.cameras[1])["rgb"])


def test_appearance_auto_follows_the_kind_of_scene():
    from recon.models.splatting_rules import uses_appearance

    scene, _ = synthetic_scene()
    cfg = config(appearance="auto")
    assert not uses_appearance(cfg, scene)
    assert uses_appearance(cfg, SceneInfo(scene.aabb, True, scene.background, 0.1, 6.0))
    import pytest

    with pytest.raises(ValueError, match="on, off or auto"):
        uses_appearance(config(appearance="yes"), scene)


def test_abs_grad_densification_auto_threshold_and_accumulators():
    """auto: absolute gradients (and their threshold) for unbounded captures only; one step's
    accumulated absolute gradient bounds the mean-gradient rule's from above (triangle
    inequality) and training with it densifies."""
    scene, data = synthetic_scene(size=24)
    unbounded = SceneInfo(scene.aabb, True, scene.background, 0.1, 6.0)
    cfg = config(densify_abs_grad="auto", densify_abs_grad_threshold=0.0002)
    assert not GaussianModel(cfg, scene).strategy.abs_grad
    assert GaussianModel(cfg, scene).strategy.grad_threshold == cfg.densify_grad_threshold
    assert GaussianModel(cfg, unbounded).strategy.abs_grad
    assert GaussianModel(cfg, unbounded).strategy.grad_threshold == 0.0002
    sums = {}
    for mode in ("off", "on"):
        model = GaussianModel(config(densify_abs_grad=mode), scene)
        train_step(model, data, 0)
        sums[mode] = model.densify_state["grad2d"]
    assert (sums["on"] >= sums["off"] - 1e-9).all() and (sums["on"] > sums["off"] + 1e-6).any()
    model = GaussianModel(config(densify_abs_grad="on", densify_abs_grad_threshold=0.0002), scene)
    counts = {train_step(model, data, step)["num_gaussians"] for step in range(45)}
    assert len(counts) > 1


def test_antialiased_model_trains_and_renders_with_compensated_opacities():
    scene, data = synthetic_scene(size=24)
    model = GaussianModel(config(antialiased=True), scene)
    for step in range(5):
        assert math.isfinite(train_step(model, data, step)["loss"])
    plain = GaussianModel(config(), scene)
    plain.load_state_dict(model.state_dict())
    out, ref = model.render(data.cameras[0]), plain.render(data.cameras[0])
    assert (out["acc"] <= ref["acc"] + 1e-6).all()  # every splat a little less opaque
    assert out["acc"].sum() < ref["acc"].sum()


def test_antialiased_splats_bake_the_mean_compensation_given_the_training_cameras():
    """What `recon export` writes: sigmoid(logit') = sigmoid(logit) x mean_compensation over
    the training cameras; without cameras, or for a model trained without antialiasing, the
    opacities are the parameters'."""
    scene, data = synthetic_scene(size=24)
    model = GaussianModel(config(antialiased=True), scene)
    for step in range(3):
        train_step(model, data, step)
    raw = model.splats()["opacity_logits"]
    assert np.array_equal(raw, model.params["opacity_logits"].detach().numpy().reshape(-1))
    baked = model.splats(data.cameras)["opacity_logits"]
    comp = mean_compensation(model.gaussians(), data.cameras, model.config.near_plane).numpy()
    sig = lambda x: 1 / (1 + np.exp(-x.astype(np.float64)))
    assert np.allclose(sig(baked), sig(raw) * comp, atol=1e-6)
    assert (comp < 1).any() and (comp <= 1).all()
    plain = GaussianModel(config(), scene)
    plain.load_state_dict(model.state_dict())
    assert np.array_equal(plain.splats(data.cameras)["opacity_logits"], raw)


def test_the_average_starts_when_densification_stops_and_resumes_exactly():
    scene, data = synthetic_scene(size=24)
    cfg = config(densify_start=5, densify_interval=10, densify_stop=30, schedule_steps=100,
                 average_window=0.05)  # fmt: skip
    model = GaussianModel(cfg, scene)
    assert [model.averaging(s) for s in (0, 29, 30, 99)] == [0, 0, 5.0, 5.0]
    assert GaussianModel(config(average_window=0.0), scene).averaging(99) == 0
    straight, resumed, _ = straight_and_resumed(cfg, scene, data, saved_at=34, steps=40)
    averages = [trainer_of(m).average for m in (straight, resumed)]
    assert averages[0].count == averages[1].count == 10  # the ends of steps 30..39
    for a, b in zip(averages[0].values, averages[1].values):
        assert torch.equal(a, b)
    last = straight.params["means"].detach().clone()
    assert trainer_of(straight).use_average() == 10
    assert not torch.equal(straight.params["means"], last)
