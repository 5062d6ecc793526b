"""The one interface of the count strategies (recon/gaussians/strategy.py): each strategy's
hooks are its own module's functions, and the model picks the strategy from its config."""

import copy
from types import SimpleNamespace

import torch

from recon.gaussians import densify, mcmc
from recon.models.splatting_rules import densify_strategy
from tests.gaussians.test_mcmc import _params
from tests.models.test_splatting import config

HOOKS = ("start", "stop", "uses_abs_grad", "regularizer", "post_backward")


def test_both_strategies_have_the_hooks_and_the_model_config_picks_one():
    adc, relocation = (
        densify_strategy(config(), False),
        densify_strategy(config(densify_mode="mcmc"), False),
    )
    assert isinstance(adc, densify.DensifyStrategy) and isinstance(relocation, mcmc.McmcStrategy)
    for strategy in (adc, relocation):
        assert all(hasattr(strategy, h) for h in HOOKS)
    assert densify_strategy(config(densify_abs_grad="on"), False).uses_abs_grad
    assert not relocation.uses_abs_grad and adc.regularizer(_params([0.5])[0]) is None


def test_mcmc_hooks_are_its_regularizer_and_post_step():
    params, optimizer = _params([0.5, 0.004, 0.9, 0.3])
    strategy = mcmc.McmcStrategy(
        cap=6, growth=0.25, opacity_reg=0.02, scale_reg=0.03, start=0, interval=1
    )
    expected = mcmc.regularizer(params, 0.02, 0.03)
    assert torch.equal(strategy.regularizer(params), expected)
    twin_params, twin_optimizer = copy.deepcopy((params, optimizer))  # one memo: linked
    state = {"kept": torch.ones(1)}
    out = strategy.post_backward(
        params, optimizer, state, None, None, 4, 2.0, 1e-4, torch.Generator().manual_seed(5)
    )
    mcmc.post_step(
        strategy, twin_params, twin_optimizer, 4, 1e-4, 2.0, torch.Generator().manual_seed(5)
    )
    assert out is state
    assert len(params["means"]) == 5  # the dead one relocated, one grown (25 % of 4)
    assert all(torch.equal(params[n], twin_params[n]) for n in params)


def test_adc_post_backward_accumulates_the_views_gradients_then_runs_the_schedule():
    params, optimizer = _params([0.5, 0.3, 0.9])
    strategy = densify.DensifyStrategy(start=0, stop=10, interval=50)
    grad = torch.tensor([[1e-3, 0.0], [0.0, 2e-3], [0.0, 0.0]])
    splats = SimpleNamespace(
        means2d=SimpleNamespace(grad=grad), radii=torch.tensor([3.0, 0.0, 1.0]), width=40, height=20
    )
    state = densify.init_state(3)
    out = strategy.post_backward(params, optimizer, state, splats, None, 2, 1.0, 1e-4, None)
    assert torch.allclose(out["grad2d"], torch.tensor([1e-3 * 20, 0.0, 0.0]))
    assert out["count"].tolist() == [1.0, 0.0, 1.0]
    abs_grad = torch.tensor([[0.0, 1e-3], [0.0, 0.0], [0.0, 0.0]])
    out = strategy.post_backward(params, optimizer, out, splats, abs_grad, 3, 1.0, 1e-4, None)
    assert torch.allclose(out["grad2d"], torch.tensor([1e-3 * 20 + 1e-3 * 10, 0.0, 0.0]))
