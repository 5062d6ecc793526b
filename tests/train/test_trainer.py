"""The trainer: the training background it chooses and hands to every loss, its optimizers
(built from the model's specs, rebuilt when the model replaces its parameters, at the
scheduled learning rates times lr_scale) and its checkpointable state."""

import pytest
import torch

from recon.cameras import Cameras
from recon.models.base import Model, OptimizerSpec, ParamGroup, TrainData
from recon.train.trainer import Trainer, training_background


class Recorder(Model):
    """A colour fitted to the images' mean; it records the background each loss was given."""

    def __init__(self, random_background="off", learned=False):
        super().__init__()
        self.color = torch.nn.Parameter(torch.zeros(3))
        self.register_buffer("background", torch.tensor([1.0, 1.0, 1.0]))
        self.random_background, self.learned = random_background, learned
        self.seen = []

    @property
    def learns_background(self):
        return self.learned

    def optimizers(self):
        schedule = lambda step: 0.1 / (1 + step)
        return {"main": OptimizerSpec([ParamGroup("color", [self.color], schedule)], kind="sgd")}

    def training_loss(self, data, step, background):
        self.seen.append(background)
        return ((self.color - data.images.mean((0, 1, 2))) ** 2).sum(), {}


def _data(alpha=False):
    images = torch.full((2, 4, 4, 3), 0.5)
    cams = Cameras(
        torch.eye(3).expand(2, 3, 3),
        torch.eye(4).expand(2, 4, 4),
        torch.full((2,), 4),
        torch.full((2,), 4),
    )
    return TrainData(images, cams, torch.ones(2, 4, 4) if alpha else None)


def test_the_training_background_is_chosen_once_and_handed_to_every_loss():
    model, data = Recorder("auto"), _data(alpha=True)
    trainer = Trainer(model)
    for step in range(3):
        trainer.step(data, step)
    assert all(b is trainer.background for b in model.seen) and trainer.background.random
    torch.testing.assert_close(trainer.background.colour, model.background)


@pytest.mark.parametrize(
    ("mode", "alpha", "learned", "random"),
    [
        ("auto", True, False, True),
        ("auto", False, False, False),  # no alpha to move the targets onto a new colour
        ("auto", True, True, False),  # an environment map is the background
        ("off", True, False, False),
        ("on", True, False, True),
    ],
)
def test_random_backgrounds_where_the_model_asks_and_the_photos_have_alpha(
    mode, alpha, learned, random
):
    assert training_background(Recorder(mode, learned), _data(alpha)).random is random


def test_random_backgrounds_without_alpha_are_refused():
    with pytest.raises(ValueError, match="needs training photos with alpha"):
        Trainer(Recorder("on")).step(_data(alpha=False), 0)


def test_learning_rates_follow_the_schedule_times_lr_scale():
    model, data = Recorder(), _data()
    trainer = Trainer(model)
    trainer.lr_scale = 0.5
    trainer.step(data, 3)
    assert trainer.optimizers["main"].param_groups[0]["lr"] == pytest.approx(0.5 * 0.1 / 4)
    # SGD: color = 0 - lr * 2 (0 - 0.5)
    torch.testing.assert_close(model.color.detach(), torch.full((3,), 0.0125))


def test_replaced_parameters_get_a_fresh_optimizer_and_state_round_trips():
    model, data = Recorder(), _data()
    trainer = Trainer(model)
    trainer.step(data, 0)
    first = trainer.optimizers["main"]
    trainer.step(data, 1)
    assert trainer.optimizers["main"] is first  # same tensors: the same optimizer
    model.color = torch.nn.Parameter(model.color.detach().clone())
    trainer.step(data, 2)
    assert trainer.optimizers["main"] is not first
    assert trainer.optimizers["main"].param_groups[0]["params"][0] is model.color
    other = Trainer(model)
    other.load_state_dict(trainer.state_dict())
    assert set(other.optimizers) == {"main"}


class Averaged(Recorder):
    """The Recorder, asking for an average of its parameters over 10 steps from step 2 on."""

    def averaging(self, step):
        return 10 if step >= 2 else 0


def test_the_run_ends_as_the_average_of_the_iterates_the_model_asked_for():
    model, data = Averaged(), _data()
    trainer = Trainer(model)
    iterates = []
    for step in range(6):
        trainer.step(data, step)
        iterates.append(model.color.detach().clone())
    # averaged from the end of step 2 on: the iterates after steps 2..5, a plain mean (< 10)
    expected = torch.stack(iterates[2:]).mean(0)
    state = trainer.state_dict()
    assert trainer.use_average() == 4
    torch.testing.assert_close(model.color.detach(), expected)
    resumed = Trainer(Averaged())  # a resumed run carries the average on
    resumed.load_state_dict(state)
    assert resumed.average.count == 4
    torch.testing.assert_close(resumed.average.values[0], expected)


def test_no_average_leaves_the_last_iterate_and_a_replaced_parameter_restarts_it():
    model, data = Recorder(), _data()
    trainer = Trainer(model)
    trainer.step(data, 0)
    last = model.color.detach().clone()
    assert trainer.use_average() == 0 and "average" not in trainer.state_dict()
    torch.testing.assert_close(model.color.detach(), last)
    model = Averaged()
    trainer = Trainer(model)
    for step in range(4):
        trainer.step(data, step)
    model.color = torch.nn.Parameter(torch.zeros(2))  # resized (as densification does)
    trainer.sync_optimizers()
    trainer._update_average(4)
    assert trainer.average.count == 1 and trainer.average.values[0].shape == (2,)
