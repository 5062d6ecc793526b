"""The trainer: what every method's training step shares (the Model / Trainer split of
nerfstudio). A model declares its optimizers as parameter groups with learning rates or
schedules (`Model.optimizers`), computes its loss (`Model.training_loss`) and acts around the
update in callbacks (`before_step`, `after_backward`, `after_step`); the trainer builds the
Adam optimizers (Kingma & Ba 2015), sets every group's learning rate for the step, runs the
backward pass and the updates, and saves and restores the optimizers' state with the model's
own (`state_dict`, `load_state_dict`). It also chooses what the training rays composite on
(`training_background`: the scene's colour, or random colours where the model's config asks
for them and the photos have alpha) and hands it to every loss.

A step, in order: `before_step`; the loss; optimizers (re)built where a model replaced its
parameters; gradients cleared; backward; `after_backward`; each due optimizer's learning rates
set (times `lr_scale`) and its update; `after_step`; where the model asks for one
(`Model.averaging`), the moving average of its parameters updated (`recon.train.averaging`),
which the run ends as (`use_average`).
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.profiler import record_function

from recon.models.background import trains_on_random_background
from recon.models.base import Model, OptimizerSpec, TrainData, TrainingBackground
from recon.train.averaging import ParameterAverage

# What a checkpoint written before the trainer existed called each optimizer's state.
LEGACY_OPTIMIZER_KEYS = {
    "optimizer": "main",
    "pose_optimizer": "pose",
    "appearance_optimizer": "appearance",
}


def build_optimizer(spec: OptimizerSpec) -> torch.optim.Optimizer:
    """The spec's optimizer over its groups (each group's "name" kept: densification finds its
    tensors by it), at the groups' learning rates for step 0."""
    groups = [
        {
            "params": list(g.params),
            "name": g.name,
            "lr": g.lr(0) if callable(g.lr) else g.lr,
            "weight_decay": g.weight_decay,
        }
        for g in spec.groups
    ]
    if spec.kind == "sgd":
        return torch.optim.SGD(groups)
    if spec.kind != "adam":
        raise ValueError(f"unknown optimizer kind {spec.kind!r} (adam, sgd)")
    return torch.optim.Adam(groups, betas=spec.betas, eps=spec.eps, fused=spec.fused)


def training_background(model: Model, data: TrainData) -> TrainingBackground:
    """The run's training background: the model's `background` colour, random colours a ray
    where its `random_background` mode asks for them (`background.trains_on_random_background`:
    "auto" where the photos have alpha and the model learns no environment map)."""
    random = trains_on_random_background(
        model.random_background, data.alpha is not None, model.learns_background
    )
    return TrainingBackground(model.background, random)


def _tensors(optimizer: torch.optim.Optimizer) -> list[int]:
    return [id(p) for group in optimizer.param_groups for p in group["params"]]


class Trainer:
    """Trains `model` one step at a time (`step`); `lr_scale` multiplies every learning rate
    (a rollback after a non-finite loss halves it for the rest of the run)."""

    def __init__(self, model: Model):
        self.model = model
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.lr_scale = 1.0
        self.background: TrainingBackground | None = None  # chosen at the first step
        self._specs: dict[str, OptimizerSpec] = {}
        self.average: ParameterAverage | None = None  # from the model's `averaging` step on
        self.sync_optimizers()

    def sync_optimizers(self) -> None:
        """A fresh optimizer for every spec whose parameters are not the tensors its optimizer
        updates (new, or replaced by the model); optimizers the model no longer has are
        dropped."""
        self._specs = self.model.optimizers()
        for name, spec in self._specs.items():
            wanted = [id(p) for g in spec.groups for p in g.params]
            current = self.optimizers.get(name)
            if current is None or _tensors(current) != wanted:
                self.optimizers[name] = build_optimizer(spec)
        for name in set(self.optimizers) - set(self._specs):
            del self.optimizers[name]

    def set_learning_rates(self, name: str, step: int) -> None:
        optimizer, spec = self.optimizers[name], self._specs[name]
        for group, declared in zip(optimizer.param_groups, spec.groups):
            lr = declared.lr(step) if callable(declared.lr) else declared.lr
            group["lr"] = lr * self.lr_scale

    def step(self, data: TrainData, step: int) -> dict[str, float | Tensor]:
        """One training step at 0-based `step` -> the scalars to log."""
        model = self.model
        if self.background is None:
            self.background = training_background(model, data)
        model.before_step(data, step)
        loss, stats = model.training_loss(data, step, self.background)
        self.sync_optimizers()  # a model may size or replace parameters in its first steps
        for optimizer in self.optimizers.values():
            optimizer.zero_grad(set_to_none=True)
        if loss.requires_grad:  # else nothing reached a parameter (every ray missed)
            with record_function("train.backward"):
                loss.backward()
            model.after_backward(data, step, stats)
            due = model.optimizers_due(step)
            with record_function("train.optimizer"):
                for name, optimizer in self.optimizers.items():
                    if due is None or name in due:
                        self.set_learning_rates(name, step)
                        optimizer.step()
        model.after_step(data, step, self.optimizers, stats)
        self._update_average(step)
        return stats

    def _update_average(self, step: int) -> None:
        """The average of the parameters after `step`, where the model asks for one; begun
        anew from them when they are not the tensors it averaged (resized or replaced)."""
        window = self.model.averaging(step)
        if not window:
            return
        params = list(self.model.parameters())
        if self.average is None or not self.average.matches(params):
            self.average = ParameterAverage(params)
        else:
            with record_function("train.average"):
                self.average.update(params, window)

    def use_average(self) -> int:
        """End as the average: the model's parameters replaced by it, in place (the
        optimizers' moments stay as they are). Returns the steps it averaged (0: none, the
        parameters are left as they are)."""
        params = list(self.model.parameters())
        if self.average is None or not self.average.matches(params):
            return 0
        self.average.copy_to(params)
        return self.average.count

    def state_dict(self) -> dict:
        """The optimizers' state and the model's own training state (`Model.training_state`)."""
        return {
            "optimizers": {name: opt.state_dict() for name, opt in self.optimizers.items()},
            "model": self.model.training_state(),
            **({"average": self.average.state_dict()} if self.average is not None else {}),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore `state_dict()` (the model's parameters already loaded). A checkpoint written
        before the trainer kept each optimizer's state among the model's own keys."""
        if "optimizers" not in state:
            optimizers = {
                new: state[old] for old, new in LEGACY_OPTIMIZER_KEYS.items() if old in state
            }
            state = {
                "optimizers": optimizers,
                "model": {k: v for k, v in state.items() if k not in LEGACY_OPTIMIZER_KEYS},
            }
        self.model.load_training_state(state["model"])
        self.optimizers = {}
        self.sync_optimizers()
        for name, saved in state["optimizers"].items():
            if name in self.optimizers:
                self.optimizers[name].load_state_dict(saved)
        self.average = None
        if "average" in state:
            device = next(self.model.parameters()).device
            self.average = ParameterAverage.from_state_dict(state["average"], device)
