"""Count control by relocation (Kheradmand et al. 2024): the relocation kernel against a worked
example and a brute-force 1D integral, the position noise's covariance, relocation and growth
of the parameters and Adam moments, and the model trained with densify_mode=mcmc."""

import math

import pytest
import torch
from torch import nn

from recon.gaussians import mcmc
from recon.gaussians.optim import make_adam
from recon.gaussians.projection import rotation_from_quats
from recon.models.splatting import GaussianModel
from recon.models.splatting_rules import densify_strategy
from tests.models.test_splatting import config, straight_and_resumed, synthetic_scene


def test_relocated_worked_example_and_single_copy():
    opacity, scales = mcmc.relocated(
        torch.tensor([0.75, 0.3]),
        torch.tensor([[1.0, 2.0, 0.5], [0.1, 0.2, 0.3]]),
        torch.tensor([2, 1]),
    )
    assert opacity.tolist() == pytest.approx([0.5, 0.3], abs=1e-7)
    assert scales[0].tolist() == pytest.approx([0.911053, 1.822106, 0.455526], abs=1e-5)
    assert scales[1].tolist() == pytest.approx([0.1, 0.2, 0.3], abs=1e-7)


@pytest.mark.parametrize(("o", "n"), [(0.75, 2), (0.2, 3), (0.5, 7), (0.95, 20), (0.999, 51)])
def test_relocated_copies_composite_to_the_original(o, n):
    """Brute force: n copies along a line through the centre, 1 - (1 - o' g'(x))^n, have the
    original's peak o and its integral o s sqrt(2 pi)."""
    opacity, scales = mcmc.relocated(torch.tensor([o]), torch.ones(1, 3), torch.tensor([n]))
    x = torch.linspace(-12, 12, 240_001, dtype=torch.float64)
    g = torch.exp(-(x**2) / (2 * float(scales[0, 0]) ** 2))
    copies = 1 - (1 - float(opacity[0]) * g) ** n
    integral = float(copies.sum() * (x[1] - x[0]))
    assert integral == pytest.approx(o * math.sqrt(2 * math.pi), rel=1e-5)
    assert float(copies.max()) == pytest.approx(o, rel=1e-5)


def test_position_noise_has_covariance_gate_squared_sigma_squared():
    """E[n n^T] = (c gate)^2 Sigma Sigma^T for noise c gate Sigma eps; opaque ones hardly move."""
    count = 200_000
    quat = torch.tensor([0.9, 0.1, -0.3, 0.2])
    log_scales = torch.log(torch.tensor([0.5, 1.0, 2.0]))
    opacity = torch.tensor([0.001, 0.5])
    noise = mcmc.position_noise(
        torch.stack([quat, quat]).repeat(count, 1),
        log_scales.repeat(2 * count, 1),
        opacity.repeat(count),
        0.3,
        torch.Generator().manual_seed(0),
    ).double()
    R = rotation_from_quats(quat).double()
    sigma = R @ torch.diag(torch.exp(2 * log_scales).double()) @ R.T
    gate = 1 / (1 + math.exp(-100 * (0.005 - 0.001)))
    expected = (0.3 * gate) ** 2 * sigma @ sigma
    moving = noise[0::2]
    measured = moving.T @ moving / count
    assert torch.allclose(measured, expected, atol=0.02 * float(expected.abs().max()))
    assert float(noise[1::2].abs().max()) < 1e-12  # gate(0.5) = sigmoid(-49.5)


def _params(opacity):
    n = len(opacity)
    gen = torch.Generator().manual_seed(1)
    params = nn.ParameterDict(
        {
            "means": nn.Parameter(torch.randn(n, 3, generator=gen)),
            "quats": nn.Parameter(torch.randn(n, 4, generator=gen)),
            "log_scales": nn.Parameter(torch.randn(n, 3, generator=gen) - 2),
            "opacity_logits": nn.Parameter(torch.logit(torch.tensor(opacity))),
            "sh_dc": nn.Parameter(torch.randn(n, 1, 3, generator=gen)),
            "sh_rest": nn.Parameter(torch.randn(n, 3, 3, generator=gen)),
        }
    )
    optimizer = make_adam(params, dict.fromkeys(params, 0.01))
    sum(p.square().sum() for p in params.values()).backward()
    optimizer.step()  # every moment non-zero
    return params, optimizer


def test_relocate_dead_moves_them_onto_live_gaussians():
    params, optimizer = _params([0.9, 0.001, 0.6, 0.004, 0.3])
    before = {k: v.detach().clone() for k, v in params.items()}
    strategy = mcmc.McmcStrategy(cap=5)
    moved = mcmc.relocate_dead(strategy, params, optimizer, torch.Generator().manual_seed(0))
    assert moved == 2 and params["means"].shape[0] == 5
    opacity = torch.sigmoid(params["opacity_logits"].detach())
    assert (opacity > strategy.min_opacity).all()
    for dead in (1, 3):  # a copy of a live Gaussian (all but opacity and scales unchanged)
        sources = [i for i in (0, 2, 4) if torch.equal(params["means"][dead], before["means"][i])]
        assert len(sources) == 1
        source = sources[0]
        for name in ("quats", "sh_dc", "sh_rest", "opacity_logits", "log_scales"):
            assert torch.equal(params[name][dead], params[name][source]), name
        copies = 1 + sum(  # itself and every dead Gaussian moved onto it
            torch.equal(params["means"][d], before["means"][source]) for d in (1, 3)
        )
        o, s = mcmc.relocated(
            torch.sigmoid(before["opacity_logits"][[source]]),
            torch.exp(before["log_scales"][[source]]),
            torch.tensor([copies]),
        )
        assert torch.allclose(opacity[source], o[0])
        assert torch.allclose(torch.exp(params["log_scales"][source]), s[0])
        state = optimizer.state[params["means"]]
        assert state["exp_avg"][[dead, source]].abs().max() == 0
    untouched = [
        i for i in (0, 2, 4) if torch.equal(params["log_scales"][i], before["log_scales"][i])
    ]
    for i in untouched:
        assert optimizer.state[params["means"]]["exp_avg"][i].abs().min() > 0


def test_grow_adds_a_growth_fraction_up_to_the_cap():
    params, optimizer = _params([0.9] * 10 + [0.5] * 10)
    gen = torch.Generator().manual_seed(0)
    assert mcmc.grow(mcmc.McmcStrategy(cap=100, growth=0.25), params, optimizer, gen) == 5
    assert params["means"].shape[0] == 25
    assert optimizer.state[params["sh_dc"]]["exp_avg_sq"].shape[0] == 25
    assert mcmc.grow(mcmc.McmcStrategy(cap=27, growth=0.25), params, optimizer, gen) == 2
    assert mcmc.grow(mcmc.McmcStrategy(cap=27, growth=0.25), params, optimizer, gen) == 0
    assert params["means"].shape[0] == 27


def test_post_step_refines_on_the_interval_and_always_adds_noise():
    params, optimizer = _params([0.001] * 4 + [0.9] * 4)
    strategy = mcmc.McmcStrategy(cap=10, growth=0.25, start=0, stop=50, interval=10)
    gen = torch.Generator().manual_seed(0)
    means = params["means"].detach().clone()
    counts = mcmc.post_step(strategy, params, optimizer, 3, 1e-4, 1.0, gen)
    assert counts == {"relocated": 0, "added": 0} and params["means"].shape[0] == 8
    assert not torch.equal(params["means"][:4], means[:4])  # transparent ones moved
    counts = mcmc.post_step(strategy, params, optimizer, 9, 1e-4, 1.0, gen)
    assert counts == {"relocated": 4, "added": 2}
    counts = mcmc.post_step(strategy, params, optimizer, 49, 1e-4, 1.0, gen)
    assert counts == {"relocated": 0, "added": 0}  # the stop


def test_model_with_mcmc_trains_grows_to_the_cap_and_resumes_exactly():
    scene, data = synthetic_scene(size=24)
    cfg = config(
        densify_mode="mcmc",
        max_gaussians=400,
        mcmc_growth=0.1,
        densify_start=5,
        densify_interval=5,
        relocate_stop=38,
    )
    assert isinstance(densify_strategy(cfg, unbounded=False), mcmc.McmcStrategy)
    model, _, _ = straight_and_resumed(cfg, scene, data, saved_at=22, steps=40)
    assert model.num_gaussians == 400
    out = model.render(data.cameras[0])
    assert torch.isfinite(out["rgb"]).all()
    auto = config(densify_mode="auto")
    assert isinstance(densify_strategy(auto, unbounded=True), mcmc.McmcStrategy)
    assert not isinstance(densify_strategy(auto, unbounded=False), mcmc.McmcStrategy)
    with pytest.raises(ValueError, match="densify_mode"):
        GaussianModel(config(densify_mode="split"), scene)
