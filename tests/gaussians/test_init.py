"""Initial Gaussians: kNN scales, the reference's conventions, random and image-guided init."""

import math

import numpy as np
import pytest
import torch

from recon.cameras import Cameras
from recon.fields.sh import C0
from recon.gaussians.init import (
    gaussians_from_points,
    image_colors,
    initial_gaussians,
    knn_scales,
    sample_in_hull,
    sample_in_shell,
)
from recon.models.base import SceneInfo, TrainData
from recon.models.splatting import GaussianModel
from recon.models.splatting_config import PRESETS, GaussiansConfig
from recon.synthetic.splats import orbit_cameras


def test_knn_scale_worked_example():
    points = np.arange(5.0)[:, None] * np.array([[1.0, 0, 0]])  # unit-spaced line
    s = knn_scales(points)
    assert s[2] == pytest.approx(math.sqrt((1 + 1 + 4) / 3))  # neighbours at 1, 1, 2
    assert s[0] == pytest.approx(math.sqrt((1 + 4 + 9) / 3))
    assert np.isfinite(knn_scales(np.zeros((3, 3)))).all()  # duplicates hit the floor


def test_init_from_points_matches_the_reference_conventions():
    points = torch.rand(20, 3)
    colors = torch.rand(20, 3)
    g = gaussians_from_points(points, colors, sh_degree=3, opacity=0.1)
    assert torch.allclose(C0 * g["sh_dc"][:, 0] + 0.5, colors, atol=1e-6)
    assert torch.allclose(torch.sigmoid(g["opacity_logits"]), torch.full((20,), 0.1))
    assert torch.equal(g["quats"], torch.tensor([[1.0, 0, 0, 0]]).expand(20, 4))
    assert g["sh_rest"].shape == (20, 15, 3) and not g["sh_rest"].any()
    assert torch.equal(g["means"], points)


def test_random_init_fills_the_box_when_there_are_no_points():
    scene = SceneInfo(
        aabb=torch.tensor([[-2.0, 0, 0], [2, 1, 3]]),
        unbounded=False,
        background=torch.zeros(3),
        near=0.1,
        far=6.0,
    )
    g = initial_gaussians(GaussiansConfig(**{**PRESETS["fast"], "init_points": 500}), scene)
    assert g["means"].shape == (500, 3)
    assert (g["means"] >= scene.aabb[0]).all() and (g["means"] <= scene.aabb[1]).all()


def one_camera(size=8):
    K = torch.tensor([[[10.0, 0, size / 2], [0, 10.0, size / 2], [0, 0, 1]]])
    return Cameras(K, torch.eye(4)[None], torch.tensor([size]), torch.tensor([size]))


def test_image_colors_reads_the_projected_pixel():
    images = torch.rand(1, 8, 8, 3)
    points = torch.tensor([[0.0, 0.0, 2.0], [0.3, -0.2, 1.0], [0.0, 0.0, -1.0]])
    colors, counts = image_colors(points, images, one_camera())
    assert torch.equal(colors[0], images[0, 4, 4])  # the axis hits pixel centre (4.5, 4.5)
    assert torch.equal(colors[1], images[0, 2, 7])  # u = 10 * 0.3 + 4 = 7, v = -2 + 4 = 2
    assert counts.tolist() == [1, 1, 0] and torch.isnan(colors[2]).all()


def test_hull_sampling_drops_background_points():
    """A white image with a red centre block: survivors project onto red, with its colour."""
    images = torch.ones(1, 8, 8, 3)
    images[0, 2:6, 2:6] = torch.tensor([1.0, 0.0, 0.0])
    aabb = torch.tensor([[-1.0, -1.0, 1.0], [1.0, 1.0, 3.0]])
    points, colors = sample_in_hull(aabb, 200, images, one_camera(), torch.ones(3), seed=0)
    assert len(points) == 200
    assert torch.equal(colors, torch.tensor([1.0, 0.0, 0.0]).expand(200, 3))
    u = 10 * points[:, 0] / points[:, 2] + 4
    assert ((u >= 2) & (u < 6)).all()
    # A background colour that never appears rejects nothing: plain random init, image colours.
    points, _ = sample_in_hull(aabb, 50, images, one_camera(), torch.zeros(3), seed=0)
    assert len(points) == 50


def test_shell_points_lie_beyond_the_cameras_with_their_image_colours():
    cameras = orbit_cameras(6, 32)  # centres at distance sqrt(3^2 + 0.5^2) from the origin
    images = torch.rand(6, 32, 32, 3)
    points, colors = sample_in_shell(
        torch.zeros(3), cameras.centers, 2.0, 300, images, cameras, seed=0
    )
    r0 = 1.1 * math.hypot(3.0, 0.5)
    r = points.norm(dim=-1)
    assert len(points) == 300 and (r >= r0 - 1e-4).all() and (r <= 2 * r0 + 1e-4).all()
    expected, counts = image_colors(points, images, cameras)
    assert (counts > 0).all() and torch.equal(colors, expected.clamp(0, 1))


@pytest.mark.parametrize("unbounded", [False, True])
def test_unbounded_image_init_also_fills_the_background(unbounded):
    """Cameras on a radius-3 orbit, scene box [-0.5, 0.5]^3: a bounded scene keeps every
    initial Gaussian in the box, an unbounded one puts init_far_fraction of them outside it."""
    cameras = orbit_cameras(6, 32)
    scene = SceneInfo(
        aabb=torch.tensor([[-0.5] * 3, [0.5] * 3]),
        unbounded=unbounded,
        background=torch.ones(3),
        near=0.1,
        far=100.0,
    )
    config = GaussiansConfig(**{**PRESETS["fast"], "init_points": 400})
    model = GaussianModel(config, scene)
    model._init_from_images(TrainData(torch.rand(6, 32, 32, 3) * 0.5, cameras))
    means = model.params["means"].detach()
    outside = (means.abs() > 0.5).any(-1).float().mean().item()
    assert model.num_gaussians == 400
    if unbounded:
        assert 0.4 < outside <= 0.5 and means.norm(dim=-1).max() > 3.3
    else:
        assert outside == 0.0
