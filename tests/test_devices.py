"""recon/devices.py: the one-read boolean selection against plain boolean indexing."""

import torch

from recon.devices import masked


def test_masked_is_boolean_indexing_of_every_tensor():
    a, b = masked(
        torch.tensor([True, False, True]), torch.tensor([1, 2, 3]), torch.tensor([[1], [2], [3]])
    )
    assert a.tolist() == [1, 3] and b.tolist() == [[1], [3]]
    gen = torch.Generator().manual_seed(0)
    mask = torch.rand(100, generator=gen) > 0.3
    x = torch.randn(100, 4, generator=gen, requires_grad=True)
    (ours,) = masked(mask, x)
    assert torch.equal(ours, x[mask])
    (g_ours,) = torch.autograd.grad(ours.sum(), x)
    (g_ref,) = torch.autograd.grad(x[mask].sum(), x)
    assert torch.equal(g_ours, g_ref)
    assert masked(torch.zeros(5, dtype=torch.bool), torch.arange(5))[0].shape == (0,)
