"""TrainData: the packed ray table and the area-downsampled levels of coarse-to-fine training."""

import torch

from recon.cameras import Cameras
from recon.cameras.cameras import intrinsics_matrix
from recon.models.base import TrainData


def _data(h=8, w=12):
    K = intrinsics_matrix(*(torch.tensor([v]) for v in (10.0, 11.0, 6.0, 4.0)))
    cams = Cameras(
        K.repeat(2, 1, 1), torch.eye(4).repeat(2, 1, 1), torch.tensor([w, w]), torch.tensor([h, h])
    )
    return TrainData(torch.rand(2, h, w, 3), cams)


def test_downsampled_is_the_block_mean_with_exact_intrinsics_and_is_cached():
    data = _data()
    half = data.downsampled(2)
    assert tuple(half.images.shape) == (2, 4, 6, 3)
    blocks = data.images.reshape(2, 4, 2, 6, 2, 3).mean((2, 4))
    assert torch.allclose(half.images, blocks, atol=1e-6)
    assert half.cameras.K[0].tolist() == [[5.0, 0.0, 3.0], [0.0, 5.5, 2.0], [0.0, 0.0, 1.0]]
    assert half.cameras.width.tolist() == [6, 6] and data.downsampled(2) is half
    assert data.downsampled(1) is data


def test_downsampled_rays_match_the_level():
    half = _data().downsampled(4)
    rays = half.rays()
    assert rays["origins"].shape == (2 * 2 * 3, 3) and torch.equal(
        rays["rgb"], half.images.reshape(-1, 3)
    )
