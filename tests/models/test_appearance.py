"""Per-image affine colour corrections: worked example, the zero-mean gauge, gradients."""

import pytest
import torch

from recon.models.appearance import AppearanceCorrection, affine_colour, centred_corrections


def test_affine_colour_worked_example():
    corr = torch.cat([2 * torch.eye(3), torch.tensor([[0.1], [0.0], [0.0]])], 1)
    out = affine_colour(torch.tensor([0.2, 0.3, 0.4]), corr)
    assert out.tolist() == pytest.approx([0.5, 0.6, 0.8])


def test_corrections_start_at_identity_and_their_mean_is_identity():
    deltas = torch.randn(7, 3, 4, dtype=torch.float64)
    corr = centred_corrections(deltas)
    assert torch.allclose(corr.mean(0), torch.eye(3, 4, dtype=torch.float64), atol=1e-12)
    assert torch.equal(centred_corrections(torch.zeros(2, 3, 4)), torch.eye(3, 4).expand(2, 3, 4))
    # the corrections depend on the deltas only up to a common shift (the gauge)
    assert torch.allclose(centred_corrections(deltas + 0.3), corr, atol=1e-12)


def test_gradients_against_finite_differences():
    deltas = torch.randn(3, 3, 4, dtype=torch.float64, requires_grad=True)
    rgb = torch.rand(5, 5, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda d, c: affine_colour(c, centred_corrections(d)[1]), (deltas, rgb)
    )


def test_learns_an_exposure_difference():
    """Two images of one grey scene, the second 20 % darker: with the scene colour learnt too,
    the corrections take the exposure difference and the scene the mean."""
    torch.manual_seed(0)
    scene = torch.nn.Parameter(torch.full((3,), 0.2))
    app = AppearanceCorrection(2, lr=1e-2)  # (no camera anchors needed for training images)
    opt = torch.optim.Adam([scene], lr=1e-2)
    app_opt = torch.optim.Adam([app.deltas], lr=app.lr, eps=1e-15)  # as the 3dgs trainer's
    targets = [torch.full((3,), 0.5), torch.full((3,), 0.4)]
    for step in range(1500):
        i = step % 2
        loss = ((app(scene, i) - targets[i]) ** 2).sum()
        opt.zero_grad(), app_opt.zero_grad()
        loss.backward()
        opt.step(), app_opt.step()
    with torch.no_grad():
        assert app(scene, 0).tolist() == pytest.approx([0.5] * 3, abs=2e-3)
        assert app(scene, 1).tolist() == pytest.approx([0.4] * 3, abs=2e-3)
        assert app.spread()["appearance_max_gain_dev"] > 0.01


def test_neighbour_correction_worked_example():
    from recon.models.appearance import neighbour_correction

    corr = torch.stack([1.2 * torch.eye(3, 4), 0.8 * torch.eye(3, 4), 5 * torch.eye(3, 4)])
    centers = torch.tensor([[1.0, 0, 0], [-3.0, 0, 0], [9.0, 0, 0]])
    directions = torch.tensor([[0.0, 0, 1]]).repeat(3, 1)
    out = neighbour_correction(
        corr, centers, directions, torch.zeros(3), torch.tensor([0.0, 0, 1]), k=2
    )
    assert out[0, 0].item() == pytest.approx(1.1)  # weights 3/4 and 1/4
    own = neighbour_correction(corr, centers, directions, centers[2], directions[2])
    assert torch.equal(own, corr[2])  # a training camera keeps its own correction
    # camera 0 is nearer (1 against 1.5) but looks the other way: d = 1 + 0.5 * 2 = 2 > 1.5
    turned = neighbour_correction(
        corr,
        torch.tensor([[1.0, 0, 0], [-1.5, 0, 0], [9.0, 0, 0]]),
        torch.tensor([[0.0, 0, -1], [0, 0, 1], [0, 0, 1]]),
        torch.zeros(3),
        torch.tensor([0.0, 0, 1]),
        k=1,
    )
    assert torch.equal(turned, corr[1])
