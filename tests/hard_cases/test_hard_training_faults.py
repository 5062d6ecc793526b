"""Non-finite values in training (never a silent NaN model). A NaN loss is caught at
once and a real run rolls back (tests/train/test_loop.py). Here: an update that writes Inf/NaN
into the PARAMETERS on a step whose loss was still finite - on the last step or right before a
checkpoint nothing would read a loss again, so the poisoned model would be kept."""

import dataclasses

import pytest
import torch

from recon.cameras import Cameras
from recon.models.base import Model, TrainData
from recon.train.config import TrainConfig
from recon.train.loop import LoopState, run_loop
from recon.train.trainer import Trainer


class Blowup(Model):
    """A constant colour fitted by SGD whose update on step `bad_step` overflows to Inf."""

    def __init__(self, bad_step: int, value: float):
        super().__init__()
        self.color = torch.nn.Parameter(torch.zeros(3))
        self.register_buffer("background", torch.zeros(3))
        self.bad_step, self.value = bad_step, value

    def optimizers(self):
        return {}  # its own update, after the backward pass

    def training_loss(self, data, step, background):
        loss = ((self.color - 0.25) ** 2).mean()
        return loss, {"loss": float(loss.detach())}

    def after_backward(self, data, step, stats):
        with torch.no_grad():
            self.color -= 0.5 * self.color.grad
            if step == self.bad_step:
                self.color[1] = self.value

    def render(self, camera):
        h, w = int(camera.height[0]), int(camera.width[0])
        return {
            "rgb": self.color.detach().expand(h, w, 3),
            "depth": torch.ones(h, w),
            "acc": torch.ones(h, w),
        }


def data():
    cams = Cameras(torch.eye(3)[None], torch.eye(4)[None], torch.tensor([4]), torch.tensor([4]))
    return TrainData(torch.full((1, 4, 4, 3), 0.25), cams)


@pytest.mark.parametrize("value", [float("inf"), float("nan")])
@pytest.mark.parametrize("checkpoint_every_s", [1e9, 0.0])  # at the end / at a checkpoint
def test_non_finite_parameters_are_never_kept(value, checkpoint_every_s):
    model, logs, saved = Blowup(bad_step=4, value=value), [], []
    cfg = TrainConfig(method="blowup", steps=5, checkpoint_every_s=checkpoint_every_s)
    with pytest.raises(FloatingPointError, match="non-finite"):
        run_loop(
            Trainer(model),
            data(),
            None,
            None,
            cfg,
            LoopState(),
            logs.append,
            lambda st: saved.append(dataclasses.replace(st)),
        )
    assert all(st.step < 5 for st in saved)  # no checkpoint of the poisoned step
    assert [e["event"] for e in logs if "event" in e] == ["non_finite_parameters"]


def test_finite_training_is_untouched():
    model, saved = Blowup(bad_step=-1, value=0.0), []
    reason = run_loop(
        Trainer(model),
        data(),
        None,
        None,
        TrainConfig(method="blowup", steps=5, checkpoint_every_s=0.0),
        LoopState(),
        lambda e: None,
        lambda st: saved.append(st.step),
    )
    assert reason == "steps" and saved == [1, 2, 3, 4, 5]
