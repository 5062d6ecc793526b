import numpy as np
import pytest
import torch

from recon.fields.sh import num_sh_bases, sh_basis
from recon.fields.sh_kernels import sh_basis_at


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_numba_basis_matches_the_torch_basis(degree):
    """`sh_basis_at` (one direction, in numba kernels) against `sh_basis`, every band."""
    dirs = torch.nn.functional.normalize(
        torch.randn(50, 3, generator=torch.Generator().manual_seed(0)), dim=-1
    )
    expected = sh_basis(degree, dirs.double())
    out = np.full(16, np.nan)
    k = num_sh_bases(degree)
    for d, e in zip(dirs.double().numpy(), expected.numpy(), strict=True):
        sh_basis_at(degree, d[0], d[1], d[2], out)
        assert np.allclose(out[:k], e, rtol=0, atol=1e-12)
    assert np.isnan(out[k:]).all()  # nothing written past the degree's bases
