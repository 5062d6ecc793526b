"""Adaptive density control: accumulators, clone / split / prune with the Adam moments carried
along, the max_gaussians cap, the opacity reset and the schedule."""

import pytest
import torch
from torch import nn

from recon.gaussians import densify
from recon.gaussians.densify import DensifyStrategy
from recon.gaussians.optim import make_adam

LRS = {
    "means": 0.01,
    "quats": 0.01,
    "log_scales": 0.01,
    "opacity_logits": 0.01,
    "sh_dc": 0.01,
    "sh_rest": 0.01,
}


def four_gaussians():
    """0: small, 1: large, 2: nearly transparent, 3: ordinary; after one Adam step."""
    params = nn.ParameterDict(
        {
            "means": nn.Parameter(torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])),
            "quats": nn.Parameter(torch.tensor([[1.0, 0, 0, 0]] * 4)),
            "log_scales": nn.Parameter(
                torch.log(torch.tensor([[0.001] * 3, [0.5, 0.2, 0.1], [0.005] * 3, [0.005] * 3]))
            ),
            "opacity_logits": nn.Parameter(torch.logit(torch.tensor([0.5, 0.5, 0.001, 0.5]))),
            "sh_dc": nn.Parameter(torch.arange(12.0).reshape(4, 1, 3)),
            "sh_rest": nn.Parameter(torch.zeros(4, 15, 3)),
        }
    )
    optimizer = make_adam(params, LRS)
    for p in params.values():
        p.grad = torch.ones_like(p)
    optimizer.step()
    state = densify.init_state(4)
    state["grad2d"] += torch.tensor([1.0, 1.0, 0.0, 0.0])  # 0 and 1 over the threshold
    state["count"] += 2.0
    return params, optimizer, state


def assert_moments_match(params, optimizer):
    for group in optimizer.param_groups:
        p = group["params"][0]
        assert p is params[group["name"]]
        for key in ("exp_avg", "exp_avg_sq"):
            assert optimizer.state[p][key].shape == p.shape, (group["name"], key)


def test_accumulate_uses_ndc_gradients_of_visible_gaussians():
    state = densify.init_state(3)
    grad = torch.tensor([[2.0, 0.0], [0.0, 4.0], [9.0, 9.0]])
    radii = torch.tensor([5.0, 10.0, 0.0])
    densify.accumulate(state, grad, radii, width=100, height=50)
    assert state["grad2d"].tolist() == pytest.approx([100.0, 100.0, 0.0])  # |g * (W/2, H/2)|
    assert state["count"].tolist() == [1.0, 1.0, 0.0]
    assert state["radii"].tolist() == pytest.approx([0.05, 0.1, 0.0])  # radius / max(W, H)


def test_pixel_weights_average_over_views_by_screen_area():
    """Pixel-GS's weighted mean sum_k m_k |g_k| / sum_k m_k, m_k = min(pi r_k^2, W H): one view
    close by (radius 20 px, NDC gradient norm 3e-4) and three far away (2 px, 1e-4 each).
    Per view the mean is (3 + 3 x 1) / 4 x 1e-4 = 1.5e-4, under a 2e-4 threshold; weighted it
    is (400 x 3 + 3 x 4 x 1) / (400 + 12) x 1e-4 = 2.9417e-4, over it."""
    W = H = 100
    plain, weighted = densify.init_state(1), densify.init_state(1)
    views = [(3e-4, 20.0), (1e-4, 2.0), (1e-4, 2.0), (1e-4, 2.0)]
    for ndc, radius in views:
        grad = torch.tensor([[ndc / (W / 2), 0.0]])  # pixel gradient with NDC norm `ndc`
        r = torch.tensor([radius])
        densify.accumulate(plain, grad, r, W, H)
        densify.accumulate(weighted, grad, r, W, H, pixel_weights=True)
    strategy = densify.DensifyStrategy(grad_threshold=2e-4)
    mean = lambda st: float(st["grad2d"][0] / st["count"][0])
    assert mean(plain) == pytest.approx(1.5e-4)
    assert mean(weighted) == pytest.approx((400 * 3 + 12) / 412 * 1e-4)
    assert not bool(densify._candidates(strategy, plain, 1)[0])
    assert bool(densify._candidates(strategy, weighted, 1)[0])
    # the area is clipped to the image: a Gaussian larger than the view weighs W H, not pi r^2
    big = densify.init_state(1)
    densify.accumulate(big, torch.tensor([[1.0, 0.0]]), torch.tensor([1000.0]), W, H, True)
    assert float(big["count"][0]) == W * H
    # invisible (radius 0) adds nothing either way
    densify.accumulate(big, torch.tensor([[1.0, 0.0]]), torch.tensor([0.0]), W, H, True)
    assert float(big["count"][0]) == W * H


def test_clone_split_prune_keep_optimizer_state_consistent():
    params, optimizer, state = four_gaussians()
    old_moment = optimizer.state[params["means"]]["exp_avg"].clone()
    parent_mean = params["means"][1].detach().clone()
    parent_scale = torch.exp(params["log_scales"][1]).detach()
    gen = torch.Generator().manual_seed(0)
    counts = densify.densify_and_prune(
        DensifyStrategy(grad_threshold=0.3),
        params,
        optimizer,
        state,
        step=10,
        scene_extent=1.0,
        generator=gen,
    )
    assert counts == {"cloned": 1, "split": 1, "pruned": 2}  # the split parent and Gaussian 2
    # Survivors in order: 0, 3 (originals), clone of 0, two children of 1.
    assert params["means"].shape[0] == 5
    assert_moments_match(params, optimizer)
    moments = optimizer.state[params["means"]]["exp_avg"]
    assert torch.equal(moments[:2], old_moment[[0, 3]])  # carried through the prune
    assert not moments[2:].any()  # new rows start from zero moments
    assert torch.equal(params["sh_dc"][2], params["sh_dc"][0])  # an exact clone
    children = torch.exp(params["log_scales"][3:])
    assert torch.allclose(children, parent_scale.expand(2, 3) / 1.6)
    offsets = params["means"][3:] - parent_mean  # sampled from N(mu, Sigma), R = I here
    assert (offsets.abs() < 4 * parent_scale).all() and offsets.abs().sum() > 0


def test_clone_opacity_correction_keeps_the_composited_alpha():
    params, optimizer, state = four_gaussians()
    o = torch.sigmoid(params["opacity_logits"][0]).item()
    strategy = DensifyStrategy(grad_threshold=0.3, clone_opacity_correction=True)
    densify.densify_and_prune(strategy, params, optimizer, state, 10, 1.0)
    # Survivors: 0, 3, clone of 0, children of 1 (see above); 0 and its clone share o'.
    halves = torch.sigmoid(params["opacity_logits"][[0, 2]]).detach()
    assert torch.equal(halves[0], halves[1])
    assert 1 - (1 - halves[0].item()) ** 2 == pytest.approx(o, rel=1e-5)
    assert torch.sigmoid(params["opacity_logits"][1]).item() == pytest.approx(0.5, rel=0.05)
    assert_moments_match(params, optimizer)


def test_max_gaussians_caps_growth_by_gradient():
    params, optimizer, state = four_gaussians()
    state["grad2d"] = torch.tensor([0.5, 1.0, 0.0, 0.0])
    strategy = DensifyStrategy(grad_threshold=0.3, max_gaussians=5)
    counts = densify.densify_and_prune(strategy, params, optimizer, state, 10, 1.0)
    assert counts["cloned"] == 0 and counts["split"] == 1  # only the larger gradient fits


def test_big_gaussians_are_pruned_only_after_the_first_reset():
    strategy = DensifyStrategy(grad_threshold=10.0, reset_interval=100, prune_world_fraction=0.1)
    for step, survivors in [(50, 3), (150, 2)]:  # Gaussian 1 (scale 0.5 > 0.1) goes at 150
        params, optimizer, state = four_gaussians()
        densify.densify_and_prune(strategy, params, optimizer, state, step, 1.0)
        assert params["means"].shape[0] == survivors
        assert_moments_match(params, optimizer)


def test_opacity_reset_clamps_and_zeroes_its_moments():
    params, optimizer, state = four_gaussians()
    strategy = DensifyStrategy(start=1000, reset_interval=100)
    faint = params["opacity_logits"][2].item()  # already below 0.01: left alone
    densify.post_step(strategy, params, optimizer, state, step=99, scene_extent=1.0)
    assert torch.sigmoid(params["opacity_logits"]).max() <= 0.01 + 1e-6
    assert params["opacity_logits"][2].item() == faint
    assert not optimizer.state[params["opacity_logits"]]["exp_avg"].any()
    assert optimizer.state[params["means"]]["exp_avg"].any()  # other attributes untouched


@pytest.mark.parametrize("step, densifies", [(99, True), (49, False), (149, False), (299, False)])
def test_schedule(step, densifies):
    """Densify when (step + 1) is a multiple of the interval, after start and before stop."""
    params, optimizer, state = four_gaussians()
    strategy = DensifyStrategy(
        grad_threshold=0.3, start=50, stop=300, interval=100, reset_interval=10_000
    )
    new_state = densify.post_step(strategy, params, optimizer, state, step, 1.0)
    assert (params["means"].shape[0] != 4) == densifies
    assert (new_state is not state) == densifies
    assert new_state["grad2d"].shape[0] == params["means"].shape[0]
