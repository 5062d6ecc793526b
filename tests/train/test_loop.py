"""The training loop's contracts: stopping rules, non-finite losses, rollback, resume."""

import dataclasses
import json

import pytest
import torch

from recon.cameras import Cameras
from recon.models.base import MethodSpec, Model, OptimizerSpec, ParamGroup, register
from recon.options import field_help
from recon.train.config import TrainConfig, apply_overrides
from recon.train.loop import LoopState, eval_due, report_progress, run_loop, should_stop
from recon.train.trainer import Trainer


@dataclasses.dataclass(frozen=True)
class ToyConfig:
    lr: float = 0.5  # step size


class Toy(Model):
    """A constant-colour model whose loss can be poisoned on chosen steps."""

    def __init__(self, poison_steps=()):
        super().__init__()
        self.color = torch.nn.Parameter(torch.zeros(3))
        self.register_buffer("background", torch.zeros(3))
        self.poison_steps = set(poison_steps)
        self.generator = torch.Generator().manual_seed(0)

    def optimizers(self):
        return {"main": OptimizerSpec([ParamGroup("color", [self.color], 0.5)], kind="sgd")}

    def training_loss(self, data, step, background):
        loss = ((self.color - data.images.mean((0, 1, 2))) ** 2).mean()
        if step in self.poison_steps:  # a transient blow-up: happens once
            self.poison_steps.discard(step)
            loss = loss * float("nan")
        return loss, {"loss": float(loss.detach())}

    def render(self, camera: Cameras):
        h, w = int(camera.height[0]), int(camera.width[0])
        return {
            "rgb": self.color.detach().expand(h, w, 3),
            "depth": torch.ones(h, w),
            "acc": torch.ones(h, w),
        }


def _data():
    from recon.models.base import TrainData

    cams = Cameras(torch.eye(3)[None], torch.eye(4)[None], torch.tensor([4]), torch.tensor([4]))
    return TrainData(torch.full((1, 4, 4, 3), 0.25), cams)


def test_stopping_rules():
    cfg = TrainConfig(method="x", steps=10)
    assert should_stop(cfg, LoopState(step=10)) == "steps"
    budget = TrainConfig(method="x", time_budget_s=1.0)
    assert should_stop(budget, LoopState(wall_s=0.5, elapsed_s=1.5)) == "time_budget"
    assert should_stop(budget, LoopState(wall_s=0.5, elapsed_s=0.5)) is None
    # the last evaluation's duration is kept in reserve for the final one
    assert (
        should_stop(budget, LoopState(wall_s=0.5, elapsed_s=0.7, eval_cost_s=0.4)) == "time_budget"
    )
    assert (
        should_stop(TrainConfig(method="x", patience=2), LoopState(evals_since_best=2))
        == "converged"
    )
    assert should_stop(cfg, LoopState(step=3)) is None


class SlowEval(Toy):
    """A Toy whose renders take `render_s` seconds: evaluations cost real time."""

    def __init__(self, render_s, on_render=lambda: None):
        super().__init__()
        self.render_s, self.on_render = render_s, on_render

    def render(self, camera):
        import time

        self.on_render()
        time.sleep(self.render_s)
        return super().render(camera)


def _held(n):
    cams = Cameras(
        torch.eye(3)[None].repeat(n, 1, 1),
        torch.eye(4)[None].repeat(n, 1, 1),
        torch.full((n,), 4),
        torch.full((n,), 4),
    )
    return cams, torch.full((n, 4, 4, 3), 0.25)


def test_time_budget_counts_evaluations():
    """Evaluations of 4 x 50 ms every 10 ms of training: a 1 s budget still ends within ~1 s of
    wall time, most of it spent evaluating, and the final evaluation fits inside it."""
    import time

    cams, imgs = _held(4)
    st, logs = LoopState(), []
    cfg = TrainConfig(method="toy", time_budget_s=1.0, eval_every_s=0.01, eval_max_fraction=0.0)
    trainer, data = Trainer(SlowEval(0.05)), _data()  # (building it: setup, not training)
    t0 = time.perf_counter()
    assert (
        run_loop(trainer, data, cams, imgs, cfg, st, logs.append, lambda s: None) == "time_budget"
    )
    took = time.perf_counter() - t0
    assert 0.8 <= st.elapsed_s <= 1.1 and took <= 1.2
    assert st.wall_s < 0.5 * st.elapsed_s  # the steps are cheap: evaluation dominates
    assert logs[-1]["test_psnr"] > 0 and logs[-1]["elapsed_s"] <= 1.1


def test_slow_evaluations_are_capped_to_a_fraction_of_the_run():
    """The same slow evaluations (4 views of 50 ms) with the default cap (0.1): the first,
    10 ms into the run, stops after its first view (the other three would break the cap) and
    keeps 0.2 s as the final one's reserve; the next probe is not due before the run is ~1 s
    old, so in 1 s only the final evaluation gives a PSNR."""
    cams, imgs = _held(4)
    st, logs = LoopState(), []
    cfg = TrainConfig(method="toy", time_budget_s=1.0, eval_every_s=0.01)
    assert cfg.eval_max_fraction == 0.1
    assert run_loop(
        Trainer(SlowEval(0.05)), _data(), cams, imgs, cfg, st, logs.append, lambda s: None
    )
    evals = [e for e in logs if "test_psnr" in e]
    assert len(evals) == 1  # the final one; uncapped: one per 10 ms
    deferred = [e for e in logs if e.get("event") == "eval_deferred"]
    assert len(deferred) == 1 and deferred[0]["eval_s"] == pytest.approx(0.05, abs=0.03)
    assert deferred[0]["projected_s"] == pytest.approx(0.2, abs=0.1)
    assert st.wall_s > 0.5 * st.elapsed_s  # training, not evaluating, fills the budget


def test_an_evaluation_that_fits_the_cap_runs_whole():
    """Views of 50 ms, the first evaluation after 1 s of training: 4 views (0.2 s) fit a cap
    of 0.5, so it gives a PSNR and nothing is deferred."""
    cams, imgs = _held(4)
    st, logs = LoopState(), []
    cfg = TrainConfig(method="toy", time_budget_s=1.6, eval_every_s=1.0, eval_max_fraction=0.5)
    run_loop(Trainer(SlowEval(0.05)), _data(), cams, imgs, cfg, st, logs.append, lambda s: None)
    assert not [e for e in logs if e.get("event") == "eval_deferred"]
    assert len([e for e in logs if "test_psnr" in e]) == 2  # the periodic one and the final


def test_a_stale_reserve_is_remeasured_so_the_budget_is_used():
    """Renders that get 20x cheaper after the first evaluation (as ngp's do once its occupancy
    grid empties): the 0.4 s reserve measured then (1.5 s into the run, under a cap of 0.5)
    is re-measured on one view near the end, and the run trains until ~0.02 s before its 3 s
    budget instead of stopping 0.4 s early."""
    cams, imgs = _held(4)
    renders = []
    model = SlowEval(0.1, on_render=lambda: renders.append(1))

    def cheaper():
        renders.append(1)
        if len(renders) == 4:  # after the first evaluation
            model.render_s = 0.005

    model.on_render = cheaper
    st, logs = LoopState(), []
    cfg = TrainConfig(method="toy", time_budget_s=3.0, eval_every_s=1.5, eval_max_fraction=0.5)
    assert run_loop(Trainer(model), _data(), cams, imgs, cfg, st, logs.append, lambda s: None)
    assert 2.9 <= st.elapsed_s <= 3.1, st.elapsed_s
    assert len([e for e in logs if "test_psnr" in e]) == 2  # the first and the final one
    assert len(renders) == 4 + 1 + 4  # first evaluation, one one-view re-measure, final


def test_progress_counts_steps_or_the_seconds_of_the_budget():
    """With --steps the bar counts steps; with --time-budget it counts seconds of the budget
    (so its ETA is the time left) and says the step; the best held-out PSNR once there is one."""
    calls = []

    def progress(*args, **info):
        calls.append((args, info))

    st = LoopState(step=40, elapsed_s=12.7)
    report_progress(progress, TrainConfig("3dgs", steps=100), st, {"psnr": 21.5})
    report_progress(progress, TrainConfig("3dgs", time_budget_s=600), st, {"psnr": 21.5})
    st.best_psnr, st.elapsed_s = 24.123, 650.0
    report_progress(progress, TrainConfig("3dgs", time_budget_s=600), st, {"psnr": 22.0})
    assert calls == [
        (("train steps", 40, 100), {"psnr": 21.5, "test_psnr": None}),
        (("train s", 12, 600), {"step": 40, "psnr": 21.5, "test_psnr": None}),
        (("train s", 600, 600), {"step": 40, "psnr": 22.0, "test_psnr": 24.12}),
    ]


def test_eval_due_worked_example():
    cfg = TrainConfig(method="toy", eval_every_s=30.0, eval_max_fraction=0.1)
    assert not eval_due(cfg, LoopState(wall_s=20.0))
    assert eval_due(cfg, LoopState(wall_s=30.0, elapsed_s=31.0))  # nothing spent yet
    # 10 s evaluations: after one at 40 s of the run the next waits until the run is 200 s
    spent = {"eval_total_s": 10.0, "eval_cost_s": 10.0, "last_eval_wall": 30.0}
    assert not eval_due(cfg, LoopState(wall_s=80.0, elapsed_s=95.0, **spent))
    assert eval_due(cfg, LoopState(wall_s=180.0, elapsed_s=190.0, **spent))
    # the same 10 s over 4 views: a 2.5 s first view fits once the run is 122.5 s old
    assert not eval_due(cfg, LoopState(wall_s=100.0, elapsed_s=110.0, **spent), views=4)
    assert eval_due(cfg, LoopState(wall_s=115.0, elapsed_s=125.0, **spent), views=4)


def test_interrupt_during_an_evaluation_stops_between_views():
    """Ctrl-C / SIGTERM (the `interrupted` flag) stop an evaluation after the view in progress,
    not after the whole evaluation."""
    cams, imgs = _held(50)
    renders = []
    model = SlowEval(0.01, on_render=lambda: renders.append(1))
    cfg = TrainConfig(method="toy", steps=100, eval_every_s=0.0, eval_max_fraction=0.0)
    with pytest.raises(KeyboardInterrupt):
        run_loop(
            Trainer(model),
            _data(),
            cams,
            imgs,
            cfg,
            LoopState(),
            lambda e: None,
            lambda s: None,
            interrupted=lambda: len(renders) >= 3,
        )
    assert len(renders) == 3 and model.training  # stopped inside the first evaluation


def test_non_finite_loss_raises_by_the_next_log():
    """The loss is read only on logged steps (every 10th: no host sync a step on a GPU), so a
    NaN at step 4 (0-based 3) is caught at step 10; a checkpoint reads it first."""
    for checkpoint_every_s, caught_at in ((1e9, 10), (0.0, 4)):
        model, logs, saved = Toy(poison_steps={3}), [], []
        with pytest.raises(FloatingPointError, match="loss became nan"):
            run_loop(
                Trainer(model),
                _data(),
                None,
                None,
                TrainConfig(method="toy", steps=20, checkpoint_every_s=checkpoint_every_s),
                LoopState(),
                logs.append,
                lambda st, saved=saved: saved.append(st.step),
            )
        events = [e["step"] for e in logs if e.get("event") == "non_finite_loss"]
        assert events == [caught_at] and all(step < 4 for step in saved)


def test_overrides_are_typed_and_validated():
    from recon.models.plenoxel import PlenoxelConfig

    out = apply_overrides(
        PlenoxelConfig, {}, ["rays_per_batch=2048", "resolutions=32,64", "lr_sh=0.5"]
    )
    assert out == {"rays_per_batch": 2048, "resolutions": (32, 64), "lr_sh": 0.5}
    with pytest.raises(ValueError, match="unknown option"):
        apply_overrides(PlenoxelConfig, {}, ["nope=1"])
    assert "coarse-to-fine" in field_help(PlenoxelConfig)["resolutions"]


def toy_workspace(tmp_path, poison_steps):
    """A workspace of a tiny Blender scene, the toy method registered with its loss poisoned
    on `poison_steps`, and a 20-step TrainConfig that checkpoints every step."""
    from recon.workspace import Workspace
    from tests.conftest import make_blender_dataset, recon_cli

    data = make_blender_dataset(tmp_path / "d")
    recon_cli("sfm", "--from-transforms", str(data), "-w", str(tmp_path / "ws"))
    register(
        MethodSpec(
            name="toy",
            config_cls=ToyConfig,
            build=lambda cfg, scene: Toy(poison_steps=poison_steps),
            presets={"fast": {}},
        )
    )
    cfg = TrainConfig(
        method="toy", steps=20, checkpoint_every_s=0.0, eval_views=1, eval_every_s=0.0
    )
    return Workspace.open(tmp_path / "ws"), cfg


def test_rollback_after_nan_in_a_real_run(tmp_path):
    from recon.train.stage import train

    ws, cfg = toy_workspace(tmp_path, poison_steps={5})
    summary = train(ws, "toy", cfg, [], resume=False, force=False, log_fn=lambda *_: None)
    assert summary["steps"] == 20 and summary["status"] == "done"
    log = [json.loads(ln) for ln in ws.log_jsonl("toy").read_text().splitlines()]
    assert [e["event"] for e in log if e.get("event") in ("non_finite_loss", "rollback")] == [
        "non_finite_loss",
        "rollback",
    ]
    rollback = next(e for e in log if e.get("event") == "rollback")
    assert rollback["lr_scale"] == 0.5 and "loss became nan" in rollback["cause"]


def test_a_run_that_keeps_failing_says_so_in_run_json_and_its_log(tmp_path):
    from recon.train.stage import MAX_ROLLBACKS, train

    ws, cfg = toy_workspace(tmp_path, poison_steps=range(3, 100))
    with pytest.raises(FloatingPointError):
        train(ws, "toy", cfg, [], resume=False, force=False, log_fn=lambda *_: None)
    doc = json.loads(ws.run_json("toy").read_text())
    assert doc["status"] == "failed" and "FloatingPointError" in doc["error"]
    log = [json.loads(ln) for ln in ws.log_jsonl("toy").read_text().splitlines()]
    assert sum(e.get("event") == "rollback" for e in log) == MAX_ROLLBACKS
    assert log[-1]["event"] == "failed"


def test_the_trainers_learning_rate_scale_multiplies_every_schedule():
    """A rollback halves `Trainer.lr_scale`: every group's rate is its schedule's times it."""
    from recon.train.trainer import Trainer

    model = Toy()
    trainer = Trainer(model)
    data = _data()
    trainer.step(data, 0)
    assert float(model.color.detach()[0]) == pytest.approx(0.5 * 2 * 0.25 / 3)  # SGD, lr 0.5
    trainer.lr_scale = 0.25
    before = model.color.detach().clone()
    trainer.step(data, 1)
    grad = 2 * (before - 0.25) / 3
    torch.testing.assert_close(model.color.detach(), before - 0.125 * grad)
    assert trainer.optimizers["main"].param_groups[0]["lr"] == 0.125


class Checker(Model):
    """Renders a 1-pixel black-and-white checkerboard at any camera size."""

    def render(self, camera: Cameras):
        h, w = int(camera.height[0]), int(camera.width[0])
        yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        rgb = ((yy + xx) % 2).float()[..., None].expand(h, w, 3)
        return {"rgb": rgb, "depth": torch.ones(h, w), "acc": torch.ones(h, w)}


def test_heldout_psnr_area_downsamples_renders_finer_than_the_photos():
    """A 1-px checkerboard rendered at 8 x 8 and a photo of the coarser level (4 x 4, its area
    average: grey 0.5) match exactly; the same board rendered straight at 4 x 4 is off by 0.5
    everywhere (6.02 dB): what the evaluation of a model that aliases when minified avoids."""
    from recon.train.loop import heldout_psnr

    def cams(n):
        K = torch.tensor([[[n, 0, n / 2], [0, n, n / 2], [0, 0, 1.0]]])
        return Cameras(K, torch.eye(4)[None], torch.tensor([n]), torch.tensor([n]))

    photos = torch.full((1, 4, 4, 3), 0.5)
    assert heldout_psnr(Checker(), cams(8), photos) > 60
    assert heldout_psnr(Checker(), cams(4), photos) == pytest.approx(6.0206, abs=1e-3)


class NoisyToy(Toy):
    """A Toy whose colour is pulled towards a different target each step (one view a step),
    asking for an average of its parameters over 4 steps from step 5 on."""

    def training_loss(self, data, step, background):
        target = 0.25 + (0.2 if step % 2 else -0.2)
        loss = ((self.color - target) ** 2).mean()
        return loss, {"loss": float(loss.detach())}

    def averaging(self, step):
        return 4 if step >= 5 else 0


def test_a_run_ends_as_the_average_and_its_final_evaluation_measures_it():
    cams, imgs = _held(1)  # held-out photos at 0.25: what the views' pulls average to
    st, logs = LoopState(), []
    trainer = Trainer(NoisyToy())
    run_loop(trainer, _data(), cams, imgs, TrainConfig(method="toy", steps=20), st, logs.append,
             lambda s: None)  # fmt: skip
    color = trainer.model.color.detach()
    torch.testing.assert_close(color, trainer.average.values[0])
    # the iterates settle into a cycle 0.21 / 0.29 (SGD: c <- c - (c - target) / 3), the last
    # one at 0.29 (28 dB); their average (window 4) within 0.04 / 7 of 0.25
    assert float((color - 0.25).abs().max()) < 0.01
    events = [e for e in logs if e.get("event") == "average"]
    assert events == [{"step": 20, "wall_s": events[0]["wall_s"], "event": "average", "steps": 15}]
    assert logs[-1]["test_psnr"] > 38.0  # measured on the average, not the last iterate
