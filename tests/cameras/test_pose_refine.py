"""Pose corrections: the pivot perturbation (worked examples, exact identity at zero, float64
gradcheck), and in the 3dgs model: off changes nothing, held-out cameras are never corrected,
exact resume, and on sample_data a perturbed training camera is pulled back to its true pose."""

import math

import pytest
import torch

from recon.cameras import Cameras
from recon.cameras.cameras import invert_rigid
from recon.cameras.pose_refine import (
    PoseCorrection,
    correct_cam_from_world,
    correction_sizes,
    outlier_ratios,
    pivot_corrections,
    pivot_depths,
)
from recon.cameras.se3 import se3_exp, se3_log, so3_exp
from recon.gaussians.render import composite_rgbd, project_splats
from recon.metrics.pose import rotation_angle_deg
from recon.models.base import TrainData
from recon.models.splatting import GaussianModel
from recon.models.splatting_config import PRESETS, GaussiansConfig
from recon.models.splatting_rules import pose_probation_end
from recon.workspace import Workspace
from recon.workspace.scene import load_scene, load_train_data
from tests.conftest import SAMPLE_DATA, recon_cli, train_step, trainer_of
from tests.models.test_splatting import config, ring, straight_and_resumed, synthetic_scene

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


def test_pivot_depths():
    cfw = torch.eye(4, dtype=F64).repeat(2, 1, 1)
    cfw[1, 2, 3] = -5.0  # the second camera has the centre behind it
    cams = Cameras(torch.eye(3).repeat(2, 1, 1), cfw, torch.tensor([4, 4]), torch.tensor([4, 4]))
    assert torch.equal(
        pivot_depths(cams, torch.tensor([0.0, 0.0, 3.0])), torch.tensor([3.0, 0.0], dtype=F64)
    )


def ring_module(n=12, seed=0):
    """A PoseCorrection for a ring of cameras around the origin, random pivots."""
    cams = ring(n=n, size=24)
    module = PoseCorrection(0)
    module.reset(cams.to(dtype=F64), torch.zeros(3))
    gen = torch.Generator().manual_seed(seed)
    module.pivots = module.pivots * (0.5 + torch.rand(n, generator=gen))
    module.set_gauge(cams.to(dtype=F64))
    return cams, module


def test_remove_gauge_drops_world_motions_and_shared_twists_only():
    cams, module = ring_module()
    gen = torch.Generator().manual_seed(3)
    eta = 1e-3 * torch.randn(6, generator=gen, dtype=F64)
    # every camera moved by one rigid motion of the world: cam_from_world M
    moved = cams.cam_from_world.double() @ se3_exp(eta)
    D = moved @ invert_rigid(cams.cam_from_world.double())  # the left corrections that do it
    P = torch.eye(4, dtype=F64).repeat(12, 1, 1)
    P[:, 2, 3] = -module.pivots.double()
    world_twists = se3_log(P @ D @ invert_rigid(P))
    shared = 1e-3 * torch.randn(6, generator=gen, dtype=F64).expand(12, 6)
    own = torch.zeros(12, 6, dtype=F64)
    own[5] = 1e-2 * torch.randn(6, generator=gen, dtype=F64)  # one camera's own correction
    with torch.no_grad():
        module.twists.copy_((world_twists + shared + own).float())
    module.remove_gauge()
    left = module.twists.detach().double()
    # what is left is the single camera's correction minus its own small gauge share
    assert torch.allclose(
        left,
        own - own.reshape(-1).matmul(module.gauge).matmul(module.gauge.T).reshape(12, 6),
        atol=1e-7,
    )
    assert (left[5] - own[5]).norm() < 0.35 * own[5].norm()
    module.remove_gauge()  # a projection: idempotent
    assert torch.allclose(module.twists.detach().double(), left, atol=1e-9)


def test_outlier_ratios_worked_example_and_gauge():
    """Block sizes (|rho|, |phi|) (1, 1), (1, 1), (1, 2), (8, 1): medians 1 and 1, ratios
    (1, 1, 2, 8). A gradient along a gauge mode (every camera's shared twist) is no one's error:
    added to every camera it changes nothing."""
    g = torch.zeros(4, 6, dtype=F64)
    g[:, 0], g[:, 4] = torch.tensor([1.0, 1, 1, 8]), torch.tensor([1.0, 1, 2, 1])
    none = torch.zeros(24, 0, dtype=F64)
    assert torch.equal(outlier_ratios(g, none), torch.tensor([1.0, 1, 2, 8], dtype=F64))
    shared = torch.eye(6, dtype=F64).repeat(4, 1) / 2.0  # orthonormal: the 6 shared twists
    common = torch.tensor([0.3, -2.0, 0.7, 1.1, 0.2, -0.5], dtype=F64)
    assert torch.allclose(outlier_ratios(g + common, shared), outlier_ratios(g, shared))
    assert outlier_ratios(g + common, none)[3] < 4  # without the gauge the outlier blurs


def test_release_frees_the_outliers_and_holds_the_rest():
    """40 cameras on a ring, 3 visits each with small random gradients; camera 7 is pulled
    along its x axis every visit (the gauge projection spreads 1/40 of that over all)."""
    _, module = ring_module(n=40)
    gen = torch.Generator().manual_seed(4)
    for visit in range(3):
        for i in range(40):
            module.twists.grad = 1e-3 * torch.randn(40, 6, generator=gen)
            if i == 7:
                module.twists.grad[7, 0] += 0.05
            module.observe(i)
    module.twists.grad = None
    module.observe(3)  # no gradient this step (e.g. an empty view): nothing counted
    assert module.visits.tolist() == [3] * 40
    assert module.release(6.0) == 1
    assert module.frozen.tolist() == [i != 7 for i in range(40)]
    # an Adam step moves every row with momentum; hold_frozen puts the frozen ones back
    optimizer = torch.optim.Adam([module.twists], lr=1e-3)
    module.twists.grad = torch.ones_like(module.twists)
    optimizer.step()
    module.hold_frozen()
    before = module.twists.detach().clone()
    module.remove_gauge()  # the frozen cameras fix the gauge now: nothing is projected out
    assert not module.twists[module.frozen].any() and module.twists[7].abs().min() > 0
    assert torch.equal(module.twists.detach(), before)
    assert module.stats()["pose_frozen"] == 39


def test_probation_end():
    assert pose_probation_end(config(pose_refine=True), 35) == 140
    assert pose_probation_end(config(pose_refine=True, pose_refine_start=10), 35) == 150
    assert pose_probation_end(GaussiansConfig(pose_refine=True), 35) == 175  # paper: 5 passes
    assert pose_probation_end(config(pose_refine=True, pose_probation=40), 35) == 40
    assert pose_probation_end(config(pose_refine=True, pose_release_ratio=0.0), 35) == 0


def test_off_or_not_yet_started_changes_nothing():
    """pose_refine off: no extra state; on but not started: the same Gaussians bit for bit."""
    scene, data = synthetic_scene(size=24)
    off = GaussianModel(config(), scene)
    idle = GaussianModel(config(pose_refine=True, pose_refine_start=10_000), scene)
    for step in range(30):
        train_step(off, data, step)
        train_step(idle, data, step)
    for name in off.params:
        assert torch.equal(off.params[name], idle.params[name]), name
    assert not any(k.startswith("pose_correction") for k in off.state_dict())
    assert "pose" not in trainer_of(off).optimizers
    assert not {"pose_rot_deg_max", "pose_shift_max"} & set(off.stats())
    assert (
        idle.pose_correction.twists.shape == (len(data), 6)
        and not idle.pose_correction.twists.any()
    )


def test_bad_pose_options_are_refused():
    scene, _ = synthetic_scene(size=24)
    for bad in (
        {"lr_pose": 0.0},
        {"lr_pose_final": -1e-6},
        {"pose_refine_start": -1},
        {"pose_release_ratio": -1.0},
    ):
        with pytest.raises(ValueError, match="pose_refine needs"):
            GaussianModel(config(pose_refine=True, **bad), scene)
    GaussianModel(config(lr_pose=0.0), scene)  # ignored while pose_refine is off


def test_training_moves_the_poses_but_never_the_held_out_cameras():
    scene, data = synthetic_scene(size=24)
    model = GaussianModel(
        config(pose_refine=True, pose_refine_start=4, lr_pose=1e-3, pose_release_ratio=0.0), scene
    )
    for step in range(20):
        train_step(model, data, step)
    twists = model.pose_correction.twists.detach()
    assert twists.abs().max() > 1e-4 and torch.allclose(twists.mean(0), torch.zeros(6), atol=1e-6)
    stats = model.stats()
    assert 0 < stats["pose_rot_deg_mean"] <= stats["pose_rot_deg_max"] < 5
    assert 0 < stats["pose_shift_mean"] <= stats["pose_shift_max"] < 0.5
    corrected = model.train_cameras(data.cameras)
    assert torch.allclose(
        corrected.cam_from_world,
        correct_cam_from_world(data.cameras.cam_from_world, twists, model.pose_correction.pivots),
    )
    held = ring(n=3, size=24)  # cameras the model never trained on
    for camera in (held[0], held[2], data.cameras[1]):  # render() takes any camera as given
        out = model.render(camera)
        with torch.no_grad():
            ref = composite_rgbd(
                project_splats(model.gaussians(), camera, int(model.active_sh_degree)),
                model.background,
            )
        assert torch.equal(out["rgb"], ref["rgb"])
    # every other training camera (`recon render --split train --every 2`) takes its own
    # correction, not the first half's
    every = model.train_cameras(data.cameras[::2], list(range(len(data.cameras)))[::2])
    assert torch.allclose(every.cam_from_world, corrected.cam_from_world[::2])
    assert not torch.allclose(
        model.train_cameras(data.cameras[::2], list(range(len(data.cameras[::2])))).cam_from_world,
        corrected.cam_from_world[::2],
    )


def test_resume_with_pose_refinement_is_exact():
    scene, data = synthetic_scene(size=24)
    cfg = config(
        densify_start=5,
        densify_interval=10,
        pose_refine=True,
        pose_refine_start=3,
        pose_release_ratio=0.0,
    )
    straight, resumed, _ = straight_and_resumed(cfg, scene, data, saved_at=17, steps=30)
    assert straight.pose_correction.twists.any()
    assert torch.equal(straight.pose_correction.twists, resumed.pose_correction.twists)
    assert torch.equal(straight.pose_correction.pivots, resumed.pose_correction.pivots)


def test_probation_moves_nothing_and_resume_keeps_its_sums_and_release():
    """A probation of 10 steps from step 2: the twists stay zero (the images at the given
    poses) while the gradient sums grow; a run resumed inside it (step 7) ends with the same
    sums, the same release at step 12 and the same twists after it as the straight run."""
    scene, data = synthetic_scene(size=24)
    cfg = config(
        densify_start=5,
        densify_interval=10,
        pose_refine=True,
        pose_refine_start=2,
        pose_probation=10,
        pose_release_ratio=1.5,
    )
    model = GaussianModel(cfg, scene)
    for step in range(12):
        train_step(model, data, step)
        pc = model.pose_correction
        assert not pc.twists.any() and int(pc.visits.sum()) == max(step - 1, 0), step
    assert pc.frozen.any() and not pc.frozen.all()  # released at the end of step 11
    straight, resumed, _ = straight_and_resumed(cfg, scene, data, saved_at=7, steps=20)
    for name in ("grad_sums", "visits", "frozen", "twists"):
        assert torch.equal(
            getattr(straight.pose_correction, name), getattr(resumed.pose_correction, name)
        ), name
    assert straight.pose_correction.twists[~straight.pose_correction.frozen].any()


@pytest.mark.slow
def test_a_perturbed_training_camera_is_pulled_back(tmp_path, one_thread):
    """sample_data at 100 x 100 px, 35 training views; view r_033 turned by 1 deg about a random
    axis through its centre and its centre moved by 2 % of the scene box's diagonal. 800 steps
    of the "fast" preset with pose_refine (default lr, probation and release ratio) bring both
    errors down >= 5x and leave the 34 exact cameras at their given poses.

    Measured: after the probation (4 passes, step 140) only r_033 is released; it ends
    0.15 deg and 0.064 x its shift off (6.7x and 15.6x). With a 5-pass probation and the
    preset's doubled scene rates the scene fits the wrong pose first: 3.3x and 6.7x."""
    ws = tmp_path / "ws"
    recon_cli("sfm", "--from-transforms", str(SAMPLE_DATA), "-w", str(ws), "--downscale", "2")
    scene = load_scene(Workspace(ws))
    data = load_train_data(Workspace(ws), scene, "train")
    view = [scene.frames[i]["name"] for i in scene.split("train")].index("r_033")
    true = data.cameras.cam_from_world.double()
    gen = torch.Generator().manual_seed(1)
    axis, direction = torch.nn.functional.normalize(
        torch.randn(2, 3, generator=gen, dtype=F64), dim=1
    )
    shift = 0.02 * float((scene.info.aabb[1] - scene.info.aabb[0]).norm())
    world_from_cam = invert_rigid(true[view])
    world_from_cam[:3, :3] = so3_exp(math.radians(1.0) * axis) @ world_from_cam[:3, :3]
    world_from_cam[:3, 3] += shift * direction
    cfw = data.cameras.cam_from_world.clone()
    cfw[view] = invert_rigid(world_from_cam).float()
    data = TrainData(
        data.images, Cameras(data.cameras.K, cfw, data.cameras.width, data.cameras.height)
    )

    config = GaussiansConfig(**{**PRESETS["fast"], "pose_refine": True, "max_gaussians": 12_000})
    model = GaussianModel(config, scene.info)
    for step in range(800):
        train_step(model, data, step)

    def errors(cam_from_world):
        rot = rotation_angle_deg(
            (cam_from_world[:, :3, :3] @ true[:, :3, :3].transpose(1, 2)).numpy()
        )
        centres = invert_rigid(cam_from_world)[:, :3, 3] - invert_rigid(true)[:, :3, 3]
        return torch.from_numpy(rot), centres.norm(dim=-1)

    rot_before, shift_before = errors(cfw.double())
    rot_after, shift_after = errors(model.train_cameras(data.cameras).cam_from_world.double())
    assert math.isclose(float(rot_before[view]), 1.0, rel_tol=1e-4)
    assert math.isclose(float(shift_before[view]), shift, rel_tol=1e-4)
    assert rot_after[view] <= rot_before[view] / 5, float(rot_after[view])
    assert shift_after[view] <= shift_before[view] / 5, float(shift_after[view])
    others = torch.arange(len(data)) != view  # the exact cameras are back at their poses
    assert model.pose_correction.frozen.tolist() == others.tolist()
    assert torch.equal(model.train_cameras(data.cameras).cam_from_world[others], cfw[others])
