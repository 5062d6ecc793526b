"""TrainData: rays of training pixels on demand and the area-downsampled levels of coarse-to-fine training."""

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


def test_rays_at_worked_example_and_camera_rays():
    """Index 7 of 2 views of 2 x 3 pixels is camera 1, row 0, column 1: its ray passes through
    the pixel centre (1.5, 0.5); every pixel's ray equals `camera_rays` of its view."""
    from recon.cameras import camera_rays

    data = _data(h=2, w=3)
    data.cameras.cam_from_world[1, :3, 3] = torch.tensor([-1.0, -2.0, -3.0])  # centre (1, 2, 3)
    ray = data.rays_at(torch.tensor([7]))
    assert ray["camera"].tolist() == [1] and torch.equal(ray["rgb"][0], data.images[1, 0, 1])
    K = data.cameras.K[1]
    through = torch.tensor([(1.5 - K[0, 2]) / K[0, 0], (0.5 - K[1, 2]) / K[1, 1], 1.0])
    assert torch.allclose(ray["directions"][0], through / through.norm())
    assert ray["origins"][0].tolist() == [1.0, 2.0, 3.0]
    rays = data.rays()
    for c in range(2):
        _, d, z = camera_rays(data.cameras, c)
        assert torch.allclose(rays["directions"][6 * c : 6 * c + 6], d.reshape(-1, 3))
        assert torch.allclose(rays["z_per_t"][6 * c : 6 * c + 6], z.reshape(-1))


def test_recomposite_worked_example_and_exactness():
    """0.6 = 0.5 * 0.2 + 0.5 * 1 on white, moved onto black: 0.1; any colour c, alpha a and
    backgrounds: a c + (1 - a) old -> a c + (1 - a) new exactly."""
    from recon.models.base import recomposite

    out = recomposite(
        torch.tensor([[0.6, 0.6, 0.6]]), torch.tensor([0.5]), torch.ones(3), torch.zeros(3)
    )
    assert torch.allclose(out, torch.full((1, 3), 0.1))
    gen = torch.Generator().manual_seed(0)
    c, a = torch.rand(5, 3, generator=gen), torch.rand(5, generator=gen)
    old, new = torch.rand(3, generator=gen), torch.rand(5, 3, generator=gen)
    on_old = a[:, None] * c + (1 - a[:, None]) * old
    assert torch.allclose(
        recomposite(on_old, a, old, new), a[:, None] * c + (1 - a[:, None]) * new, atol=1e-6
    )


def test_alpha_follows_the_rays_and_the_levels():
    data = _data()
    data = TrainData(data.images, data.cameras, torch.rand(2, 8, 12))
    rays = data.rays_at(torch.tensor([0, 13, 191]))
    assert torch.equal(rays["alpha"], data.alpha.reshape(-1)[[0, 13, 191]])
    half = data.downsampled(2)
    assert torch.allclose(half.alpha, data.alpha.reshape(2, 4, 2, 6, 2).mean((2, 4)), atol=1e-6)
    assert "alpha" not in _data().rays_at(torch.tensor([0]))


def test_random_training_backgrounds_move_transparent_pixels_onto_their_ray_colour():
    """alpha 0: the target becomes the drawn colour; alpha 1: unchanged; alpha 0.5 on white
    (rgb 0.6 = 0.5 * 0.2 + 0.5): 0.1 + 0.5 * new."""
    import torch

    from recon.models.base import TrainingBackground

    batch = {
        "rgb": torch.tensor([[1.0, 1.0, 1.0], [0.3, 0.4, 0.5], [0.6, 0.6, 0.6]]),
        "alpha": torch.tensor([0.0, 1.0, 0.5]),
    }
    white = torch.ones(3)
    target, new = TrainingBackground(white, True).targets(batch, torch.Generator().manual_seed(0))
    assert new.shape == (3, 3) and ((new >= 0) & (new < 1)).all()
    torch.testing.assert_close(target[0], new[0])
    torch.testing.assert_close(target[1], batch["rgb"][1])
    torch.testing.assert_close(target[2], 0.1 + 0.5 * new[2])
    plain, none = TrainingBackground(white).targets(batch, torch.Generator().manual_seed(0))
    assert plain is batch["rgb"] and none is None
