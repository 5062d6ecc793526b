"""Pose corrections: the pivot perturbation (worked examples, exact identity at zero, float64
gradcheck), and in the 3dgs model: off changes nothing, held-out cameras are never corrected,
exact resume, and on sample_data a perturbed training camera is pulled back to its true pose."""

import io
import math

import torch

from recon.cameras import Cameras
from recon.cameras.cameras import invert_rigid
from recon.cameras.pose_refine import (
    PoseCorrection,
    correct_cam_from_world,
    correction_sizes,
    pivot_corrections,
    pivot_depths,
)
from recon.cameras.se3 import se3_exp
from recon.gaussians.model import GaussianModel
from recon.gaussians.render import composite_rgbd, project_splats
from tests.test_gaussians_model import config, ring, synthetic_scene

F64 = torch.float64


def random_rigid(n, seed):
    gen = torch.Generator().manual_seed(seed)
    return se3_exp(torch.randn(n, 6, generator=gen, dtype=F64))


def test_zero_twists_return_the_cameras_exactly():
    cfw = random_rigid(5, seed=0)
    pivots = torch.rand(5, dtype=F64) * 3
    assert torch.equal(correct_cam_from_world(cfw, torch.zeros(5, 6), pivots), cfw)
    assert torch.equal(correct_cam_from_world(cfw.float(), torch.zeros(5, 6), pivots), cfw.float())


def test_rotation_turns_the_camera_about_its_pivot():
    """90 deg about the camera's y axis with the pivot at depth 2: the pivot (0, 0, 2) stays put
    and the centre moves along the chord of a quarter circle of radius 2, |t| = 2 sqrt(2)."""
    twist = torch.tensor([[0.0, 0, 0, 0, math.pi / 2, 0]], dtype=F64)
    D = pivot_corrections(twist, torch.tensor([2.0], dtype=F64))[0]
    assert torch.allclose(D[:3, 3], torch.tensor([-2.0, 0, 2.0], dtype=F64), atol=1e-15)
    pivot = torch.tensor([0.0, 0, 2, 1], dtype=F64)
    assert torch.allclose(D @ pivot, pivot, atol=1e-15)
    degrees, shift = correction_sizes(twist, torch.tensor([2.0]))
    assert math.isclose(float(degrees[0]), 90.0) and math.isclose(float(shift[0]), 2 * math.sqrt(2))


def test_zero_pivot_is_the_plain_left_perturbation_and_sizes_match_the_centres():
    gen = torch.Generator().manual_seed(1)
    twists = 0.3 * torch.randn(6, 6, generator=gen, dtype=F64)
    assert torch.allclose(pivot_corrections(twists, torch.zeros(6)), se3_exp(twists), atol=1e-15)
    cfw = random_rigid(6, seed=2)
    pivots = torch.rand(6, generator=gen, dtype=F64) * 2
    moved = correct_cam_from_world(cfw, twists, pivots)
    centre_shift = (invert_rigid(moved)[:, :3, 3] - invert_rigid(cfw)[:, :3, 3]).norm(dim=-1)
    degrees, shift = correction_sizes(twists, pivots)
    assert torch.allclose(shift, centre_shift, atol=1e-12)
    rel = moved[:, :3, :3] @ cfw[:, :3, :3].transpose(1, 2)
    cos = ((rel.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1)
    assert torch.allclose(torch.rad2deg(torch.acos(cos)), degrees, atol=1e-6)


def test_correction_gradcheck_float64():
    cfw = random_rigid(3, seed=3)
    pivots = torch.tensor([0.0, 1.0, 2.5], dtype=F64)
    twists = (0.2 * torch.randn(3, 6, dtype=F64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda t: correct_cam_from_world(cfw, t, pivots), (twists,))


def test_pivot_depths_and_centering():
    cfw = torch.eye(4, dtype=F64).repeat(2, 1, 1)
    cfw[1, 2, 3] = -5.0  # the second camera has the centre behind it
    cams = Cameras(torch.eye(3).repeat(2, 1, 1), cfw, torch.tensor([4, 4]), torch.tensor([4, 4]))
    assert torch.equal(pivot_depths(cams, torch.tensor([0.0, 0.0, 3.0])),
                       torch.tensor([3.0, 0.0], dtype=F64))
    module = PoseCorrection(0)
    module.reset(cams, torch.tensor([0.0, 0.0, 3.0]))
    with torch.no_grad():
        module.twists += torch.tensor([[1.0, 2, 3, 4, 5, 6], [3, 2, 1, 0, -1, -2]])
    module.center()
    assert torch.equal(module.twists.detach(), torch.tensor([[-1.0, 0, 1, 2, 3, 4], [1, 0, -1, -2, -3, -4]]))


def test_off_or_not_yet_started_changes_nothing():
    """pose_refine off: no extra state; on but not started: the same Gaussians bit for bit."""
    scene, data = synthetic_scene(size=24)
    off = GaussianModel(config(), scene)
    idle = GaussianModel(config(pose_refine=True, pose_refine_start=10_000), scene)
    for step in range(30):
        off.train_step(data, step)
        idle.train_step(data, step)
    for name in off.params:
        assert torch.equal(off.params[name], idle.params[name]), name
    assert not any(k.startswith("pose_correction") for k in off.state_dict())
    assert "pose_optimizer" not in off.training_state()
    assert not {"pose_rot_deg_max", "pose_shift_max"} & set(off.stats())
    assert idle.pose_correction.twists.shape == (len(data), 6) and not idle.pose_correction.twists.any()


def test_training_moves_the_poses_but_never_the_held_out_cameras():
    scene, data = synthetic_scene(size=24)
    model = GaussianModel(config(pose_refine=True, pose_refine_start=4, lr_pose=1e-3), scene)
    for step in range(20):
        model.train_step(data, step)
    twists = model.pose_correction.twists.detach()
    assert twists.abs().max() > 1e-4 and torch.allclose(twists.mean(0), torch.zeros(6), atol=1e-7)
    stats = model.stats()
    assert 0 < stats["pose_rot_deg_mean"] <= stats["pose_rot_deg_max"] < 5
    assert 0 < stats["pose_shift_mean"] <= stats["pose_shift_max"] < 0.5
    corrected = model.train_cameras(data.cameras)
    assert torch.allclose(corrected.cam_from_world, correct_cam_from_world(
        data.cameras.cam_from_world, twists, model.pose_correction.pivots))
    held = ring(n=3, size=24)  # cameras the model never trained on
    for camera in (held[0], held[2], data.cameras[1]):  # render() takes any camera as given
        out = model.render(camera)
        with torch.no_grad():
            ref = composite_rgbd(project_splats(model.gaussians(), camera,
                                                int(model.active_sh_degree)), model.background)
        assert torch.equal(out["rgb"], ref["rgb"])


def test_resume_with_pose_refinement_is_exact():
    scene, data = synthetic_scene(size=24)
    cfg = config(densify_start=5, densify_interval=10, pose_refine=True, pose_refine_start=3)
    straight = GaussianModel(cfg, scene)
    for step in range(30):
        straight.train_step(data, step)
    first = GaussianModel(cfg, scene)
    for step in range(17):
        first.train_step(data, step)
    buffer = io.BytesIO()
    torch.save({"model": first.state_dict(), "training": first.training_state()}, buffer)
    buffer.seek(0)
    saved = torch.load(buffer, weights_only=True)
    resumed = GaussianModel(cfg, scene)
    resumed.load_state_dict(saved["model"])
    resumed.load_training_state(saved["training"])
    for step in range(17, 30):
        resumed.train_step(data, step)
    for name in straight.params:
        assert torch.equal(straight.params[name], resumed.params[name]), name
    assert straight.pose_correction.twists.any()
    assert torch.equal(straight.pose_correction.twists, resumed.pose_correction.twists)
    assert torch.equal(straight.pose_correction.pivots, resumed.pose_correction.pivots)
