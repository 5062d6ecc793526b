"""Blending-weight contributions: the identity sum_i C_i = sum_p (1 - T_final), the dense
reference twin, the lowest-fraction rule, and pruning at the end of densification in the model."""

import dataclasses

import pytest
import torch

from recon.gaussians.contribution import contributions, least_contributing, view_contributions
from recon.gaussians.rasterize import rasterize_features
from recon.gaussians.rasterize_reference import rasterize_features_reference
from recon.gaussians.render import project_splats
from recon.models.splatting import GaussianModel
from recon.models.splatting_rules import prune_fraction
from tests.conftest import train_step, trainer_of
from tests.gaussians.test_rasterize import random_splats
from tests.models.test_splatting import config, synthetic_scene


def test_contributions_sum_to_the_covered_area():
    scene, data = synthetic_scene(size=40)
    model = GaussianModel(config(init_points=200), scene)
    g, cams = model.gaussians(), data.cameras
    total = contributions(g, cams, 0, 0.01)
    covered = 0.0
    for i in range(len(cams)):
        s = project_splats({k: v.detach() for k, v in g.items()}, cams[i], 0, 0.01)
        ones = torch.ones(len(s.opacities), 1)
        _, T = rasterize_features(
            s.means2d, s.conics, s.opacities, ones, s.radii, s.depths, s.width, s.height
        )
        covered += float((1 - T).double().sum())
    assert total.shape == (200,) and (total >= 0).all()
    assert abs(float(total.sum()) - covered) < 1e-4 * covered


def test_view_contributions_match_the_dense_reference():
    W, H = 37, 29
    means2d, conics, opacities, _, radii, depths = random_splats(60, W, H, seed=2)
    ones = torch.ones(60, 1, dtype=torch.float64, requires_grad=True)
    image, _ = rasterize_features_reference(means2d, conics, opacities, ones, radii, depths, W, H)
    (expected,) = torch.autograd.grad(image.sum(), ones)
    ones = torch.ones(60, 1, dtype=torch.float64, requires_grad=True)
    image, _ = rasterize_features(means2d, conics, opacities, ones, radii, depths, W, H)
    (fast,) = torch.autograd.grad(image.sum(), ones)
    assert torch.allclose(fast, expected, atol=1e-10)
    assert (expected[radii == 0] == 0).all()


def test_view_contributions_is_the_weight_sum_of_one_camera():
    scene, data = synthetic_scene(size=32)
    model = GaussianModel(config(init_points=50), scene)
    one = view_contributions(model.gaussians(), data.cameras[0], 0, 0.01)
    both = contributions(model.gaussians(), data.cameras[[0, 0]], 0, 0.01)
    assert torch.allclose(2 * one.double(), both)


def test_least_contributing_worked_example():
    drop = least_contributing(torch.tensor([3.0, 1.0, 2.0, 0.0]), 0.5)
    assert drop.tolist() == [False, True, False, True]
    assert not least_contributing(torch.tensor([1.0, 1.0, 1.0]), 0.0).any()


def test_pruning_when_densification_ends_halves_the_count_and_keeps_training():
    scene, data = synthetic_scene()
    model = GaussianModel(config(densify_stop=60, prune_contribution=0.5), scene)
    counts = [train_step(model, data, step)["num_gaussians"] for step in range(80)]
    before, after = counts[58], counts[59]
    assert after == before - int(0.5 * before)
    assert all(c == after for c in counts[59:])
    for group in (
        trainer_of(model).optimizers["main"].param_groups
    ):  # moments follow the pruned rows
        p = group["params"][0]
        if p in trainer_of(model).optimizers["main"].state:
            assert trainer_of(model).optimizers["main"].state[p]["exp_avg"].shape == p.shape


def test_auto_prunes_bounded_scenes_only_and_bad_fractions_are_refused():
    scene, _ = synthetic_scene()
    assert prune_fraction(config(), scene) == 0.5
    unbounded = dataclasses.replace(scene, unbounded=True)
    assert prune_fraction(config(), unbounded) == 0.0
    assert prune_fraction(config(prune_contribution=0.3), unbounded) == 0.3
    for bad in (1.0, -0.5):
        with pytest.raises(ValueError, match="prune_contribution"):
            GaussianModel(config(prune_contribution=bad), scene)


def test_no_pruning_in_a_run_too_short_to_densify():
    scene, data = synthetic_scene()
    model = GaussianModel(config(densify_start=20, densify_stop=10), scene)
    counts = [train_step(model, data, step)["num_gaussians"] for step in range(12)]
    assert counts[-1] == counts[0]
