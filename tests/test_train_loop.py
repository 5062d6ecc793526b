"""The training loop's contracts: stopping rules, non-finite losses, rollback, resume."""

import dataclasses
import json

import pytest
import torch

from recon.cameras import Cameras
from recon.models.base import MethodSpec, Model, register
from recon.train.config import TrainConfig, apply_overrides, field_help
from recon.train.loop import LoopState, run_loop, should_stop


@dataclasses.dataclass(frozen=True)
class ToyConfig:
    lr: float = 0.5  # step size


class Toy(Model):
    """A constant-colour model whose loss can be poisoned on chosen steps."""

    def __init__(self, poison_steps=()):
        super().__init__()
        self.color = torch.nn.Parameter(torch.zeros(3))
        self.opt = torch.optim.SGD([self.color], lr=0.5)
        self.poison_steps = set(poison_steps)
        self.generator = torch.Generator().manual_seed(0)

    def train_step(self, data, step):
        loss = ((self.color - data.images.mean((0, 1, 2))) ** 2).mean()
        if step in self.poison_steps:  # a transient blow-up: happens once
            self.poison_steps.discard(step)
            loss = loss * float("nan")
        self.opt.zero_grad()
        loss.backward()
        self.opt.step()
        return {"loss": float(loss.detach())}

    def render(self, camera: Cameras):
        h, w = int(camera.height[0]), int(camera.width[0])
        return {"rgb": self.color.detach().expand(h, w, 3), "depth": torch.ones(h, w), "acc": torch.ones(h, w)}


def _data():
    from recon.models.base import TrainData

    cams = Cameras(torch.eye(3)[None], torch.eye(4)[None], torch.tensor([4]), torch.tensor([4]))
    return TrainData(torch.full((1, 4, 4, 3), 0.25), cams)


def test_stopping_rules():
    cfg = TrainConfig(method="x", steps=10)
    assert should_stop(cfg, LoopState(step=10)) == "steps"
    assert should_stop(TrainConfig(method="x", time_budget_s=1.0), LoopState(wall_s=1.5)) == "time_budget"
    assert should_stop(TrainConfig(method="x", patience=2), LoopState(evals_since_best=2)) == "converged"
    assert should_stop(cfg, LoopState(step=3)) is None


def test_non_finite_loss_raises_at_once():
    model, logs = Toy(poison_steps={3}), []
    with pytest.raises(FloatingPointError):
        run_loop(model, _data(), None, None, TrainConfig(method="toy", steps=10), LoopState(), logs.append,
                 lambda st: None)
    assert any(e.get("event") == "non_finite_loss" for e in logs)


def test_overrides_are_typed_and_validated():
    from recon.models.plenoxel import PlenoxelConfig

    out = apply_overrides(PlenoxelConfig, {}, ["rays_per_batch=2048", "resolutions=32,64", "lr_sh=0.5"])
    assert out == {"rays_per_batch": 2048, "resolutions": (32, 64), "lr_sh": 0.5}
    with pytest.raises(ValueError, match="unknown option"):
        apply_overrides(PlenoxelConfig, {}, ["nope=1"])
    assert "coarse-to-fine" in field_help(PlenoxelConfig)["resolutions"]


def test_rollback_after_nan_in_a_real_run(tmp_path):
    from recon.train.stage import train
    from recon.workspace import Workspace
    from tests.conftest import make_blender_dataset, recon_cli

    data = make_blender_dataset(tmp_path / "d")
    recon_cli("sfm", "--from-transforms", str(data), "-w", str(tmp_path / "ws"))
    register(MethodSpec(name="toy", config_cls=ToyConfig, build=lambda cfg, scene: Toy(poison_steps={5}),
                        presets={"fast": {}}))
    ws = Workspace.open(tmp_path / "ws")
    cfg = TrainConfig(method="toy", steps=20, checkpoint_every_s=0.0, eval_views=1, eval_every_s=0.0)
    summary = train(ws, "toy", cfg, [], resume=False, force=False, log_fn=lambda *_: None)
    assert summary["steps"] == 20 and summary["status"] == "done"
    log = [json.loads(ln) for ln in ws.log_jsonl("toy").read_text().splitlines()]
    assert [e["event"] for e in log if e.get("event") in ("non_finite_loss", "rollback")] == ["non_finite_loss", "rollback"]
    rollback = next(e for e in log if e.get("event") == "rollback")
    assert rollback["lr_scale"] == 0.5 and "loss became nan" in rollback["cause"]


def test_learning_rate_scale_applies_during_step_only():
    from recon.train.stage import LearningRateScale

    p = torch.nn.Parameter(torch.zeros(1))
    opt = torch.optim.SGD([p], lr=0.3)
    with LearningRateScale() as scale:
        p.grad = torch.ones(1)
        opt.step()
        assert float(p.detach()) == pytest.approx(-0.3)
        scale.scale = 0.25
        opt.step()
        assert float(p.detach()) == pytest.approx(-0.3 - 0.075)
        assert opt.param_groups[0]["lr"] == 0.3  # the schedule's value is restored exactly
    opt.step()  # hooks removed on exit
    assert float(p.detach()) == pytest.approx(-0.3 - 0.075 - 0.3)
