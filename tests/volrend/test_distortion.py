"""mip-NeRF 360's distortion loss: the worked example, the O(S^2) definition as a twin on values
and gradients, and its limiting cases."""

import torch

from recon.volrend.distortion import distortion_loss, distortion_loss_reference


def test_worked_example():
    w = torch.tensor([0.5, 0.5])
    s0, s1 = torch.tensor([0.0, 1.0]), torch.tensor([1.0, 2.0])
    torch.testing.assert_close(
        distortion_loss(w, s0, s1, torch.tensor([0, 0]), 1), torch.tensor([2 / 3])
    )


def test_packed_prefix_sums_match_the_pairwise_definition_on_values_and_gradients():
    g = torch.Generator().manual_seed(0)
    R, S = 5, 9
    edges = torch.sort(torch.rand(R, S + 1, generator=g, dtype=torch.float64), -1).values
    w = torch.rand(R, S, generator=g, dtype=torch.float64)
    w = (
        w / w.sum(-1, keepdim=True) * torch.rand(R, 1, generator=g, dtype=torch.float64)
    ).requires_grad_()
    dense = distortion_loss_reference(w, edges[:, :-1], edges[:, 1:])
    (g_dense,) = torch.autograd.grad(dense.sum(), w)
    # packed: drop some samples (as occupancy skipping does) from both layouts alike
    keep = torch.rand(R, S, generator=g) > 0.3
    keep[3] = False  # a ray without any sample
    ri = torch.arange(R)[:, None].expand(R, S)[keep]
    packed = distortion_loss(w[keep], edges[:, :-1][keep], edges[:, 1:][keep], ri, R)
    masked = distortion_loss_reference(w * keep, edges[:, :-1], edges[:, 1:])
    torch.testing.assert_close(packed, masked)
    assert packed[3] == 0
    full = distortion_loss(
        w.reshape(-1),
        edges[:, :-1].reshape(-1),
        edges[:, 1:].reshape(-1),
        torch.arange(R).repeat_interleave(S),
        R,
    )
    torch.testing.assert_close(full, dense)
    (g_packed,) = torch.autograd.grad(full.sum(), w)
    torch.testing.assert_close(g_packed, g_dense)


def test_limits_one_interval_and_a_spread_ray():
    # all weight in one interval of length l: only the self term, w^2 l / 3
    w, s0, s1 = (
        torch.tensor([0.0, 1.0, 0.0]),
        torch.tensor([0.0, 0.2, 0.5]),
        torch.tensor([0.2, 0.5, 1.0]),
    )
    torch.testing.assert_close(
        distortion_loss(w, s0, s1, torch.zeros(3, dtype=torch.long), 1), torch.tensor([0.1])
    )
    # the same total weight spread over the ray costs more than concentrated
    n = 100
    edges = torch.linspace(0, 1, n + 1)
    spread = distortion_loss(
        torch.full((n,), 1 / n), edges[:-1], edges[1:], torch.zeros(n, dtype=torch.long), 1
    )
    torch.testing.assert_close(
        spread, torch.tensor([1 / 3]), atol=1e-4, rtol=0
    )  # E|x - y| = 1/3 on U[0, 1]
    assert spread > 10 * distortion_loss(
        torch.tensor([1.0]),
        torch.tensor([0.5]),
        torch.tensor([0.51]),
        torch.zeros(1, dtype=torch.long),
        1,
    )
