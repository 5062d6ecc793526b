"""What the volume models composite behind their samples: the random-background rule, and nerf's
and ngp's training renders on a per-ray background colour."""

import math
from dataclasses import replace

import pytest
import torch

from recon.cameras.rays import camera_rays
from recon.models.background import trains_on_random_background
from recon.models.base import TrainData
from recon.models.nerf import NeRFModel
from recon.models.ngp import NGPModel
from recon.train.trainer import training_background
from tests.conftest import train_step
from tests.models.test_nerf import SMALL as NERF_SMALL
from tests.models.test_ngp import SMALL as NGP_SMALL
from tests.models.test_ngp import sphere_scene

pytestmark = pytest.mark.usefixtures("one_thread")


def test_random_background_rule():
    """auto: on with alpha and a fixed background only; on without alpha (or with a learned
    environment) is an error; off is off."""
    assert trains_on_random_background("auto", has_alpha=True, learned=False)
    assert not trains_on_random_background("auto", has_alpha=False, learned=False)
    assert not trains_on_random_background("auto", has_alpha=True, learned=True)
    assert not trains_on_random_background("off", has_alpha=True, learned=False)
    assert trains_on_random_background("on", has_alpha=True, learned=False)
    for has_alpha, learned in ((False, False), (True, True)):
        with pytest.raises(ValueError, match="needs training photos with alpha"):
            trains_on_random_background("on", has_alpha, learned)
    with pytest.raises(ValueError, match="must be auto, on or off"):
        trains_on_random_background("maybe", True, False)


def _rays(data, n=300):
    o, d, _ = camera_rays(data.cameras, 0)
    return o.reshape(-1, 3)[:n], d.reshape(-1, 3)[:n]


def _nerf_render(model, o, d, background):
    state = model.generator.get_state()
    _, fine = model._render_rays(o, d, jitter=True, background=background)
    model.generator.set_state(state)  # the same jittered samples for the next render
    return fine["rgb"], fine["acc"]


def _ngp_render(model, o, d, background):
    state = model.generator.get_state()
    out = model._render_rays_train(o, d, background)[0]
    model.generator.set_state(state)
    return out.rgb, out.acc


@pytest.mark.parametrize(
    "build, render",
    [
        (lambda info: NeRFModel(replace(NERF_SMALL, occupancy_warmup=0), info), _nerf_render),
        (lambda info: NGPModel(NGP_SMALL, info), _ngp_render),
    ],
    ids=["nerf", "ngp"],
)
def test_a_given_background_moves_every_ray_by_its_transmittance(build, render):
    """C(b) = sum w c + (1 - acc) b: rendered on per-ray colours b instead of the model's own
    background, each ray (hit or missed) moves by exactly (1 - acc)(b - background)."""
    data, info, _ = sphere_scene(n_cams=2, size=24)
    model = build(info)
    o, d = _rays(data, 576)
    with torch.no_grad():
        own, acc = render(model, o, d, None)
        b = torch.rand(o.shape[0], 3, generator=torch.Generator().manual_seed(1))
        moved, acc_b = render(model, o, d, b)
    torch.testing.assert_close(acc_b, acc)
    assert (1 - acc).max() > 0.1  # the background shows through
    torch.testing.assert_close(
        moved - own, (1 - acc)[:, None] * (b - model.background), atol=1e-5, rtol=1e-4
    )


@pytest.mark.parametrize(
    "build",
    [
        lambda info, m: NeRFModel(replace(NERF_SMALL, random_background=m), info),
        lambda info, m: NGPModel(replace(NGP_SMALL, random_background=m), info),
    ],
    ids=["nerf", "ngp"],
)
def test_training_on_random_backgrounds_where_the_photos_have_alpha(build):
    data, info, _ = sphere_scene(n_cams=2, size=16)
    with_alpha = TrainData(data.images, data.cameras, torch.ones(data.images.shape[:3]))
    model = build(info, "auto")
    assert training_background(model, with_alpha).random
    assert not training_background(model, data).random
    assert math.isfinite(train_step(model, with_alpha, 0)["loss"])
    assert not training_background(build(info, "off"), with_alpha).random
    with pytest.raises(ValueError, match="must be auto, on or off"):
        build(info, "sometimes")


def test_the_outer_volume_starts_behind_the_box_and_falls_back_to_its_environment():
    """Rays that hit the box start at its exit, rays that miss it at their closest approach to
    its centre; with no density out there a ray sees exactly the environment map, and the
    colour is differentiable in both the field and the map."""
    from recon.models.background import OuterVolume

    torch.manual_seed(0)
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    outer = OuterVolume(aabb, near=0.1, far=100.0, n_samples=8)
    o = torch.tensor([[0.0, 0.0, -5.0], [3.0, 0.0, -5.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    start = outer.start(o, d, torch.tensor([6.0, 0.0]), torch.tensor([True, False]))
    torch.testing.assert_close(start, torch.tensor([6.0, 5.0]))  # exit z = 1; closest at z = 0
    rgb = outer(o, d, start, jitter=False)
    assert rgb.shape == (2, 3) and ((rgb > 0) & (rgb < 1)).all()
    rgb.sum().backward()
    assert outer.grid.table.grad.abs().sum() > 0  # the field is learnt
    with torch.no_grad():
        outer.density_mlp[-1].bias[0] = -60.0  # sigma = exp(-60): empty
    outer.zero_grad()
    empty = outer(o, d, start, jitter=False)
    torch.testing.assert_close(empty, outer.environment(d))
    empty.sum().backward()  # the map behind is learnt through what the volume leaves open
    assert outer.environment.net[2].weight.grad.abs().sum() > 0


def test_sdf_with_an_outer_volume_trains_and_renders():
    from recon.models.sdf import SDFConfig, SDFModel

    data, info, _ = sphere_scene(n_cams=2, size=12)
    cfg = SDFConfig(outer_volume="on", n_levels=4, log2_table_size=12, n_max=64, rays_per_batch=64)
    model = SDFModel(cfg, info)
    assert model.outer is not None and model.environment is None
    assert math.isfinite(train_step(model, data, 0)["loss"])
    assert model.outer.grid.table.grad is not None  # the backdrop is learnt with the object
    out = model.render(data.cameras[0])
    assert out["rgb"].shape == (12, 12, 3) and torch.isfinite(out["rgb"]).all()
    with pytest.raises(ValueError, match="outer_volume must be on or off"):
        SDFModel(replace(cfg, outer_volume="auto"), info)
