"""The one learning-rate decay: the worked example, its limits, and the log-linear form the
3DGS means schedule was written in before (a twin)."""

import math

import pytest
import torch

from recon.models.schedules import exp_decay_lr, set_lr


def test_worked_example_and_limits():
    assert exp_decay_lr(500, 1e-2, 1e-3, 1000) == pytest.approx(1e-2 * 10**-0.5)  # 3.16e-3
    assert exp_decay_lr(0, 1e-2, 1e-3, 1000) == 1e-2
    assert exp_decay_lr(5000, 1e-2, 1e-3, 1000) == pytest.approx(1e-3)
    assert exp_decay_lr(300, 1e-2, 1e-3, 1000, start=400) == 1e-2  # held until start
    assert exp_decay_lr(700, 1e-2, 1e-3, 1000, start=400) == pytest.approx(1e-2 * 10**-0.5)


@pytest.mark.parametrize("step", [0, 1, 777, 29_999, 30_000, 40_000])
def test_equals_the_log_linear_interpolation(step):
    lr, final, n = 1.6e-4, 1.6e-6, 30_000
    t = min(step / n, 1.0)
    log_linear = math.exp((1 - t) * math.log(lr) + t * math.log(final))
    assert exp_decay_lr(step, lr, final, n) == pytest.approx(log_linear, rel=1e-12)


def test_set_lr_all_groups_or_one_named_group():
    a, b = torch.nn.Parameter(torch.zeros(1)), torch.nn.Parameter(torch.zeros(1))
    opt = torch.optim.Adam(
        [{"params": [a], "name": "means"}, {"params": [b], "name": "sh"}], lr=1.0
    )
    set_lr(opt, 0.5, "means")
    assert [g["lr"] for g in opt.param_groups] == [0.5, 1.0]
    set_lr(opt, 0.25)
    assert [g["lr"] for g in opt.param_groups] == [0.25, 0.25]


def test_fit_schedules_worked_example():
    from dataclasses import dataclass

    from recon.models.schedules import fit_schedules

    @dataclass(frozen=True)
    class Toy:
        schedule_steps: int = 1600
        lr_decay_steps: int = 5000
        densify_stop: int = 2000

    fractions = {"lr_decay_steps": 1.0, "densify_stop": 0.7}
    assert fit_schedules(Toy(), fractions) == Toy(1600, 1600, 1120)
    assert fit_schedules(Toy(schedule_steps=0), fractions) == Toy(0)  # not planned
    assert fit_schedules(Toy(schedule_steps=9000), fractions) == Toy(9000)  # long enough


def test_refit_schedules_worked_example_and_limits():
    """Mid-run re-fits follow the latest estimate, never beyond the plan; a schedule never ends
    in the past (one that would ends at the next step); one already ended, or an interval
    already fired, stays as it was."""
    from dataclasses import dataclass

    from recon.models.schedules import refit_schedules

    @dataclass(frozen=True)
    class Toy:
        schedule_steps: int = 3359
        lr_decay_steps: int = 3359
        densify_stop: int = 2351
        reset_interval: int = 1176

    fractions = {"lr_decay_steps": 1.0, "densify_stop": 0.7, "reset_interval": 0.35}
    plan = Toy()

    def refit(current, steps, step):
        return refit_schedules(plan, current, fractions, steps, step)

    # the reset not yet fired is due at once (735 is past), then keeps its interval
    shorter = refit(plan, 2100, 1000)
    assert shorter == Toy(2100, 2100, 1470, 1001)
    assert refit(shorter, 2500, 1200) == Toy(2500, 2500, 1750, 1001)  # grows back
    assert refit(shorter, 9000, 1200) == Toy(3359, 3359, 2351, 1001)  # never beyond the plan
    assert refit(plan, 2100, 1600) == Toy(2100, 2100, 1601, 1176)
    assert refit(plan, 2100, 700) == Toy(2100, 2100, 1470, 735)
    assert refit(plan, 4000, 1000) == plan  # longer than planned: unchanged
    unplanned = Toy(0, 5000, 2000, 1000)
    assert refit_schedules(unplanned, unplanned, fractions, 2100, 10) == unplanned
    ended = Toy(1500, 1500, 900, 400)  # densification over, a reset fired
    assert refit(ended, 1100, 1000) == Toy(1100, 1100, 900, 400)
    assert refit(ended, 3000, 1000) == Toy(3000, 3000, 900, 400)
