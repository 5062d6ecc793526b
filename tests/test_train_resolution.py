"""The working-resolution rule: worked examples on the real scene sizes, and the overrides."""

import dataclasses

import pytest

from recon.models.base import ResolutionPolicy
from recon.train.resolution import MIN_SIDE, choose_resolution, downscale_for_max_side, epochs_at

# a policy of 350k px/s (3dgs's before it was measured on a quiet machine): worked examples
SPLATS = ResolutionPolicy(pixels_per_s=350e3, pixels_per_step=0.0, min_epochs=30.0, max_side=1600)
RAYS = ResolutionPolicy(pixels_per_s=12e3, pixels_per_step=3000.0, min_epochs=1.0, max_side=800)
FOX = (1076, 1913, 58)  # recon sfm's undistorted fox photos, 58 training views


def test_epochs_worked_example():
    # 600 s * 350k px/s over 58 views of 269 x 478 = 2.1e8 / 7.458e6 = 28.2 passes
    assert epochs_at(269, 478, 58, SPLATS, 600, 0, 2) == pytest.approx(28.16, abs=0.01)
    assert epochs_at(269, 478, 58, SPLATS, 600, 0, 4) == pytest.approx(
        2 * 28.16, abs=0.02
    )  # 4 threads
    # a --steps run of a whole-image-per-step method makes steps / views passes at any size
    assert epochs_at(269, 478, 58, SPLATS, 0, 5800, 2) is None
    assert epochs_at(100, 100, 10, RAYS, 0, 1000, 2) == pytest.approx(30.0)  # 3e6 rays / 1e5 px


def test_fox_ten_minutes_at_350k_px_per_s_trains_at_one_fifth():
    res = choose_resolution(*FOX, SPLATS, time_budget_s=600)
    assert (res.downscale, res.width, res.height, res.source) == (5, 215, 382, "auto")
    assert "44 passes" in res.reason and "1/4 would give 28" in res.reason


def test_the_3dgs_policy_on_fox_by_budget():
    """3dgs's own policy on the fox capture: the levels the fox-real benchmark trains at."""
    from recon.models.splatting import RESOLUTION

    levels = [
        choose_resolution(*FOX, RESOLUTION, time_budget_s=b).downscale
        for b in (120, 300, 600, 1800)
    ]
    assert levels == [9, 6, 4, 3]


def test_more_time_means_a_finer_level():
    levels = [
        choose_resolution(*FOX, SPLATS, time_budget_s=t).downscale for t in (120, 600, 1800, 7200)
    ]
    assert levels == sorted(levels, reverse=True) and levels[0] > levels[-1]


def test_lego_200_keeps_its_size():
    # 100 views of 200 x 200 in 600 s: 52 passes at full size
    for policy in (SPLATS, RAYS):
        res = choose_resolution(200, 200, 100, policy, time_budget_s=600)
        assert (res.downscale, res.width, res.height) == (1, 200, 200)


def test_without_a_size_dependent_budget_the_cap_decides():
    for kw in ({}, {"steps": 3000}, {"patience": 0}):
        kw.pop("patience", None)
        res = choose_resolution(*FOX, SPLATS, **kw)
        assert res.downscale == 2 and max(res.width, res.height) <= 1600  # 956 px
    gpu = choose_resolution(*FOX, SPLATS, time_budget_s=60, cpu=False)
    assert gpu.downscale == 2 and "throughput" in gpu.reason


def test_never_coarser_than_the_floor():
    res = choose_resolution(*FOX, SPLATS, time_budget_s=1)
    assert (
        max(res.width, res.height)
        <= MIN_SIDE
        < max(res.width, res.height) * res.downscale / (res.downscale - 1)
    )
    assert "not coarser" in res.reason


def test_user_options_override():
    assert choose_resolution(*FOX, SPLATS, time_budget_s=600, downscale=3).downscale == 3
    res = choose_resolution(*FOX, SPLATS, time_budget_s=600, max_side=500)
    assert (res.downscale, res.source) == (4, "max_side") and max(res.width, res.height) <= 500


def test_downscale_for_max_side():
    assert downscale_for_max_side(1076, 1913, 1913) == 1
    assert downscale_for_max_side(1076, 1913, 1912) == 2
    assert downscale_for_max_side(200, 200, 1600) == 1


def test_every_method_keeps_lego_200_at_its_size_under_the_protocol_budgets():
    """The lego-200 protocol (100 views of 200 x 200; 600 s, nerf 1800 s) trains at full size."""
    from recon.models.registry import import_methods

    budgets = {"nerf": 1800}
    for name, spec in import_methods().items():
        res = choose_resolution(
            200, 200, 100, spec.resolution, time_budget_s=budgets.get(name, 600)
        )
        assert res.downscale == 1, (name, res.reason)


def test_planned_steps_worked_example():
    from recon.train.resolution import planned_steps

    assert planned_steps(269, 478, SPLATS, 600, 0, 2) == 1633  # 600 * 350e3 / 128582
    assert planned_steps(269, 478, SPLATS, 600, 1000, 2) == 1000  # --steps comes first
    assert planned_steps(269, 478, RAYS, 600, 0, 2) == 2400  # 600 * 12e3 / 3000 rays a step
    assert (
        planned_steps(269, 478, SPLATS, 0, 0, 2) == 0
        and planned_steps(269, 478, SPLATS, 600, 0, 2, cpu=False) == 0
    )
    affine = dataclasses.replace(SPLATS, step_overhead_s=0.05, step_pixels_per_s=1e6)
    assert planned_steps(269, 478, affine, 600, 0, 2) == 3359  # 600 / (0.05 + 128582 / 1e6)
    assert planned_steps(269, 478, affine, 600, 0, 4) == 6719  # twice the threads
    assert planned_steps(358, 638, affine, 1800, 0, 2) == 6465  # fox-real made 6,479


def test_3dgs_plans_the_fox_real_runs_within_ten_percent_of_their_steps():
    """The steps the 3dgs policy plans for the four quiet fox-real runs (2, 5, 10, 30 min at
    the levels the rule chose) against the steps they made (commits a87c7be, 4497ef7)."""
    from recon.models.splatting import RESOLUTION
    from recon.train.resolution import planned_steps

    made = {(120, 119, 212): 1623, (300, 179, 319): 2625, (600, 269, 478): 3642}
    made[(1800, 358, 638)] = 6479
    for (budget, w, h), steps in made.items():
        plan = planned_steps(w, h, RESOLUTION, budget, 0, 2)
        assert abs(plan - steps) < 0.1 * steps, (budget, plan, steps)
