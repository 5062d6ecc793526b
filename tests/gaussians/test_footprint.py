"""The training footprint at render time (recon.gaussians.footprint): the dilation in world
units, its worked example, the conic / opacity algebra against a direct inverse, and the limiting
case that defines it: a render at 2x with the training camera's footprint samples the same
continuous image as the training-size render."""

import math
from dataclasses import replace

import pytest
import torch

from recon.cameras import Cameras
from recon.gaussians.footprint import footprint_dilation, with_training_footprint
from recon.gaussians.mip_filter import sampling_intervals
from recon.gaussians.projection import DILATION
from recon.gaussians.render import ProjectedSplats, composite_rgbd, project_splats
from tests.conftest import train_step


def test_footprint_dilation_worked_example():
    T, z = torch.tensor([0.01]), torch.tensor([2.0])
    assert footprint_dilation(z, T, 400.0).item() == pytest.approx(1.2)  # (400 * 0.01 / 2)^2 0.3
    assert footprint_dilation(z, T, 100.0).item() == pytest.approx(DILATION)  # coarser: 0.3


def _splats(cov: torch.Tensor, opacity: torch.Tensor, depths: torch.Tensor) -> ProjectedSplats:
    dilated = cov + DILATION * torch.eye(2, dtype=cov.dtype)
    inv = torch.linalg.inv(dilated)
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
    n = len(cov)
    radii = torch.full((n,), 5.0, dtype=cov.dtype)
    z = torch.zeros(n, 2, dtype=cov.dtype)
    return ProjectedSplats(z, conics, depths, radii, opacity, torch.zeros(n, 3), 64, 64)


@pytest.mark.parametrize("antialiased", [False, True])
def test_conics_opacities_and_radii_against_a_direct_inverse(antialiased):
    g = torch.Generator().manual_seed(0)
    a = torch.randn(6, 2, 2, generator=g, dtype=torch.float64)
    cov = a @ a.transpose(1, 2) * 0.2  # SPD, about a pixel
    det = torch.linalg.det(cov)
    base = torch.rand(6, generator=g, dtype=torch.float64)
    comp = torch.sqrt(det / torch.linalg.det(cov + DILATION * torch.eye(2, dtype=cov.dtype)))
    opacity = base * comp if antialiased else base
    depths = torch.full((6,), 2.0, dtype=torch.float64)
    T = torch.tensor([0.01, 0.02, 0.005, 0.0, 0.01, 0.03], dtype=torch.float64)
    out = with_training_footprint(_splats(cov, opacity, depths), T, 400.0, antialiased)
    d = footprint_dilation(depths, T, 400.0)
    want = cov + d[:, None, None] * torch.eye(2, dtype=cov.dtype)
    inv = torch.linalg.inv(want)
    assert torch.allclose(out.conics, torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1))
    expect = base * torch.sqrt(det / torch.linalg.det(want)) if antialiased else base
    assert torch.allclose(out.opacities, expect)
    lam = torch.linalg.eigvalsh(want)[:, -1]
    assert torch.equal(out.radii, torch.maximum(torch.ceil(3 * lam.sqrt()), torch.tensor(5.0)))
    # splats the render does not magnify (T = 0.005 and 0: f T / z <= 1) are untouched
    for i in (2, 3):
        assert torch.equal(out.conics[i], _splats(cov, opacity, depths).conics[i])


def _camera(focal: float, size: int, cx: float) -> Cameras:
    K = torch.tensor([[[focal, 0, cx], [0, focal, cx], [0, 0, 1]]], dtype=torch.float64)
    return Cameras(
        K, torch.eye(4, dtype=torch.float64)[None], torch.tensor([size]), torch.tensor([size])
    )


@pytest.mark.parametrize("antialiased", [False, True])
def test_a_2x_render_samples_the_training_size_image(antialiased):
    """Gaussians far below a pixel, seen by one training camera (f = 40, 32 px): rendered by
    the camera 2x finer with each splat's training footprint, the 2x pixels that sit on the
    1x pixel centres (principal point 2 cx - 0.5) equal the training-size render; without it
    the small splats shrink to a quarter of their area and the image differs."""
    g = torch.Generator().manual_seed(1)
    n = 60
    gauss = {
        "means": torch.cat(
            [torch.rand(n, 2, generator=g) * 2 - 1, 3 + torch.rand(n, 1, generator=g)], 1
        ).double(),
        "quats": torch.randn(n, 4, generator=g).double(),
        "log_scales": (torch.rand(n, 3, generator=g) * 2 - 5.5).double(),  # 0.004-0.03: < 1 px
        "opacity_logits": torch.randn(n, generator=g).double(),
        "sh_dc": torch.rand(n, 1, 3, generator=g).double(),
        "sh_rest": torch.zeros(n, 0, 3, dtype=torch.float64),
    }
    train = _camera(40.0, 32, 16.0)
    fine = _camera(80.0, 64, 31.5)
    T = sampling_intervals(gauss["means"], train)
    bg = torch.zeros(3, dtype=torch.float64)
    low = composite_rgbd(project_splats(gauss, train, 0, antialiased=antialiased), bg)["rgb"]
    plain = project_splats(gauss, fine, 0, antialiased=antialiased)
    kept = with_training_footprint(plain, T, 80.0, antialiased)
    high = composite_rgbd(kept, bg)["rgb"][::2, ::2]
    assert (low - high).abs().max() < 1e-9  # the same samples of the same image
    drift = (low - composite_rgbd(plain, bg)["rgb"][::2, ::2]).abs().max()
    assert drift > 0.05
    assert math.isfinite(float(high.sum()))


def test_a_finished_model_renders_its_training_views_as_before_and_finer_views_with_footprints():
    from recon.models.splatting import GaussianModel
    from tests.models.test_splatting import config, synthetic_scene

    scene, data = synthetic_scene(size=24)
    model = GaussianModel(config(), scene)
    for step in range(30):
        train_step(model, data, step)
    cam = data.cameras[0]
    before = model.render(cam)["rgb"]
    model.finish(data)
    assert len(model.filter_intervals) == model.num_gaussians
    assert torch.equal(model.render(cam)["rgb"], before)  # no splat is magnified there
    fine = cam.resized(96, 96)
    with_fp = model.render(fine)["rgb"]
    model.config = replace(model.config, footprint_filter=False)
    assert not torch.equal(model.render(fine)["rgb"], with_fp)
