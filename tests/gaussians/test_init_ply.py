"""`init_ply` (`recon train --init-from-ply`): a model exported as a world-frame splat PLY and
read back into a new model renders the same image at step 0."""

import numpy as np
import torch

from recon.cameras.conventions import rotation_from_quat_wxyz
from recon.cameras.similarity import Similarity
from recon.gaussians.init import gaussians_from_splat_ply, sh_degree_in_use
from recon.gaussians.ply import write_splat_ply
from recon.gaussians.transform import gaussians_to_world
from recon.models.base import SceneInfo
from recon.models.splatting import GaussianModel
from recon.models.splatting_config import GaussiansConfig
from recon.synthetic.splats import orbit_cameras, shell_gaussians


def _similarity(seed: int = 3) -> Similarity:
    rng = np.random.default_rng(seed)
    return Similarity(0.37, rotation_from_quat_wxyz(rng.normal(size=4)), rng.normal(size=3))


def _scene(sim: Similarity | None) -> SceneInfo:
    return SceneInfo(
        aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]),
        unbounded=False,
        background=torch.tensor([1.0, 1.0, 1.0]),
        near=0.1,
        far=6.0,
        points=torch.rand(50, 3) * 2 - 1,
        point_colors=torch.rand(50, 3),
        scene_from_world=sim,
    )


def _export_world_ply(model: GaussianModel, sim: Similarity, path) -> None:
    """What `recon export` writes: the scene-frame Gaussians in world units."""
    p = {k: v.detach().double().numpy() for k, v in model.params.items()}
    g = {
        "means": p["means"],
        "quats": p["quats"],
        "log_scales": p["log_scales"],
        "opacity_logits": p["opacity_logits"],
        "sh": np.concatenate([p["sh_dc"], p["sh_rest"]], 1),
    }
    w = gaussians_to_world(g, sim.scale, sim.R, sim.t)
    write_splat_ply(path, w["means"], w["quats"], w["log_scales"], w["opacity_logits"], w["sh"])


def _trained_like_model(sim: Similarity) -> GaussianModel:
    """A model with the attributes training produces: rotated, anisotropic, degree-3 colours."""
    model = GaussianModel(GaussiansConfig(), _scene(sim))
    g = shell_gaussians(400, seed=5)
    for name, value in g.items():
        model.params[name] = torch.nn.Parameter(value)
    model.active_sh_degree.fill_(3)
    return model


def _exported(tmp_path, seed: int = 3) -> tuple[Similarity, GaussianModel, object]:
    """A similarity, a trained-like model and its world-frame PLY."""
    sim = _similarity(seed)
    original = _trained_like_model(sim)
    path = tmp_path / "splat.ply"
    _export_world_ply(original, sim, path)
    return sim, original, path


def test_round_trip_renders_the_same_image(tmp_path):
    sim, original, path = _exported(tmp_path)
    restored = GaussianModel(GaussiansConfig(init_ply=str(path)), _scene(sim))
    assert restored.num_gaussians == original.num_gaussians
    assert int(restored.active_sh_degree) == 3  # the file's SH are used from step 0
    camera = orbit_cameras(4, 64)[1]
    a, b = original.render(camera), restored.render(camera)
    # float32 storage and the world round trip: ~1e-6 per attribute, well below one 8-bit level
    assert (a["rgb"] - b["rgb"]).abs().max() < 1e-4
    assert (a["acc"] - b["acc"]).abs().max() < 1e-4
    assert (a["rgb"] - 1.0).abs().max() > 0.1  # the view does show the Gaussians


def test_ply_attributes_return_to_the_scene_frame(tmp_path):
    sim, original, path = _exported(tmp_path, 7)
    back, degree = gaussians_from_splat_ply(path, sim, 3)
    p = original.params
    assert degree == 3
    assert torch.allclose(back["means"], p["means"].detach(), atol=1e-5)
    assert torch.allclose(back["log_scales"], p["log_scales"].detach(), atol=1e-5)
    q0 = p["quats"].detach() / p["quats"].detach().norm(dim=-1, keepdim=True)
    q1 = back["quats"] / back["quats"].norm(dim=-1, keepdim=True)
    assert torch.allclose((q0 * q1).sum(-1).abs(), torch.ones(len(q0)), atol=1e-5)  # q ~ -q
    assert torch.allclose(back["sh_rest"], p["sh_rest"].detach(), atol=1e-4)


def test_lower_model_degree_drops_the_higher_coefficients(tmp_path):
    sim, _, path = _exported(tmp_path, 2)
    back, degree = gaussians_from_splat_ply(path, sim, 1)
    assert degree == 1 and back["sh_rest"].shape == (400, 3, 3)


def test_sh_degree_in_use():
    sh = np.zeros((2, 16, 3))
    assert sh_degree_in_use(sh) == 0
    sh[1, 5, 2] = 0.1  # a degree-2 coefficient
    assert sh_degree_in_use(sh) == 2


def test_init_ply_needs_the_similarity(tmp_path):
    _, _, path = _exported(tmp_path)
    try:
        GaussianModel(GaussiansConfig(init_ply=str(path)), _scene(None))
    except ValueError as e:
        assert "scene_from_world" in str(e)
    else:
        raise AssertionError("expected a ValueError")
