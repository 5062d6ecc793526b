"""Re-planning a budgeted run from its measured step rate: the projection's worked example,
the windows, and the loop handing a shorter run to the model."""

import dataclasses

import pytest

from recon.train.config import TrainConfig
from recon.train.loop import LoopState, run_loop
from recon.train.replan import Replanner, projected_steps
from recon.train.trainer import Trainer


def test_projected_steps_worked_example():
    assert projected_steps(1000, 3.0, 0.95, 600.0, 300.0, 10.0) == 1826
    assert projected_steps(1000, 3.0, 1.0, 600.0, 700.0, 10.0) == 1000  # past the budget


def test_windows_warm_up_then_project_at_the_recent_rate():
    """30-s windows: the first only warms up; the second projects at its own rate (2.5 steps
    per second of training, not the first window's 10) over the time left, scaled by the run's
    training share."""
    planner = Replanner(600.0, 0, 0.0, 0.0, every_s=30.0, warmup_windows=1)
    assert planner.after_step(100, 10.0, 10.0, 0.0) is None
    assert planner.after_step(300, 30.0, 30.0, 0.0) is None  # warm-up
    assert planner.after_step(320, 40.0, 50.0, 0.0) is None
    # window 30 -> 60 s: 60 steps in 24 s of training; 54 of 60 s spent training so far
    assert (
        planner.after_step(360, 54.0, 60.0, 0.0)
        == projected_steps(360, 2.5, 0.9, 600.0, 60.0, 0.0)
        == 1575
    )
    assert planner.after_step(361, 54.5, 61.0, 0.0) is None


@dataclasses.dataclass
class Planned:
    """The schedule a test model lays out: 10,000 steps, shortened by `replan` (shrink only)."""

    schedule_steps: int = 10_000
    calls: list = dataclasses.field(default_factory=list)


def test_a_budgeted_loop_hands_the_model_a_shorter_run(monkeypatch):
    import time

    from recon.train import replan
    from tests.train.test_loop import Toy, _data

    class Slow(Toy):
        def __init__(self):
            super().__init__()
            self.plan = Planned()

        def training_loss(self, data, step, background):
            time.sleep(0.005)
            return super().training_loss(data, step, background)

        def replan(self, schedule_steps, step):
            self.plan.calls.append((schedule_steps, step))
            if schedule_steps >= self.plan.schedule_steps:
                return 0
            self.plan.schedule_steps = schedule_steps
            return schedule_steps

    monkeypatch.setattr(replan, "REPLAN_EVERY_S", 0.1)
    model, st, logs = Slow(), LoopState(), []
    cfg = TrainConfig(method="toy", time_budget_s=1.0)
    assert run_loop(Trainer(model), _data(), None, None, cfg, st, logs.append, lambda s: None)
    assert len(model.plan.calls) >= 5  # ~9 windows after the warm-up one
    projected, at_step = model.plan.calls[0]
    assert at_step < projected < 1.3 * 1.0 / 0.005  # at most ~200 steps fit in 1 s
    assert st.schedule_steps == model.plan.schedule_steps < 10_000
    assert st.schedule_steps == pytest.approx(st.step, rel=0.3)  # the plan met the run
    events = [e for e in logs if e.get("event") == "replan"]
    assert events and events[-1]["schedule_steps"] == st.schedule_steps
    # a --steps run has no budget to re-plan against
    model, st = Slow(), LoopState()
    run_loop(
        Trainer(model), _data(), None, None, TrainConfig("toy", steps=30), st, logs.append, print
    )
    assert model.plan.calls == [] and st.schedule_steps == 0


def test_a_budgeted_run_plans_its_schedules_on_any_device():
    """The plan (and so the re-plan, which never lengthens past it) comes from the budget at
    the device's measured speed, a GPU's too: a device 20x faster plans ~20x the steps, the
    paper preset's schedules scaled into them."""
    from recon.models.registry import method_spec
    from recon.train.resolution import WorkingResolution, plan_schedules
    from recon.train.throughput import REFERENCE, Speed

    spec = method_spec("3dgs")
    paper = spec.config_cls(**spec.presets["paper"])
    cfg = TrainConfig(method="3dgs", time_budget_s=600)
    res = WorkingResolution(2, 538, 956, "auto", "")
    cpu = plan_schedules(paper, spec, cfg, res, REFERENCE).schedule_steps
    gpu = plan_schedules(paper, spec, cfg, res, Speed(20.0, 20.0, "measured")).schedule_steps
    assert (cpu, gpu) == (1063, 21264)  # 600 / (0.05 + 514,328 px / 1M px/s), then / 20
    assert plan_schedules(paper, spec, TrainConfig("3dgs", steps=500), res, REFERENCE) == (
        dataclasses.replace(paper, schedule_steps=500)
    )
