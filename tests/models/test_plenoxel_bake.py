"""Baking a field into a Plenoxels lattice (`recon.models.plenoxel_bake`, `PlenoxelModel.bake`)."""

import math

import pytest
import torch

from recon.fields.sh import eval_sh, sh_basis
from recon.models.ngp import NGPModel
from recon.models.plenoxel import PlenoxelModel
from recon.models.plenoxel_bake import (
    bake_lattice,
    fibonacci_directions,
    fit_sh_logits,
    lattice_points,
    vertices_in_cells,
)
from recon.models.registry import save_model
from tests.conftest import sphere_scene, train_step
from tests.models.test_ngp import SMALL
from tests.models.test_plenoxel import sphere_config

pytestmark = pytest.mark.usefixtures("one_thread")


def test_fibonacci_directions_worked_example_and_spread():
    d = fibonacci_directions(2)
    assert torch.allclose(d[0], torch.tensor([0.8660, 0.0, 0.5]), atol=1e-4)
    assert torch.allclose(d[1], torch.tensor([-0.6386, 0.5850, -0.5]), atol=1e-4)
    many = fibonacci_directions(400)
    assert torch.allclose(many.norm(dim=-1), torch.ones(400), atol=1e-6)
    assert many.mean(0).abs().max() < 0.01  # spread evenly: no preferred side
    # the degree-2 SH basis is well conditioned on 32 of them (the bake's default)
    assert torch.linalg.matrix_rank(sh_basis(2, fibonacci_directions(32)).double()) == 9


def test_sh_fit_recovers_the_coefficients_of_a_sigmoid_sh_colour():
    g = torch.Generator().manual_seed(0)
    coeffs = torch.randn(5, 9, 3, generator=g)
    dirs = fibonacci_directions(32)
    rgb = torch.sigmoid(eval_sh(2, coeffs[:, None], dirs[None, :]))  # (5, 32, 3)
    fitted = fit_sh_logits(rgb, sh_basis(2, dirs))
    assert torch.allclose(fitted, coeffs, atol=2e-4)
    # colours at 0 or 1 have no finite logit: they are clamped, not inf
    assert torch.isfinite(fit_sh_logits(torch.ones(1, 32, 3), sh_basis(2, dirs))).all()


def test_lattice_points_and_vertices_in_cells():
    assert torch.equal(
        lattice_points(torch.tensor([0, 1, 4, 4 + 16 * 3]), 4),
        torch.tensor([[0, 0, 0], [1 / 3, 0, 0], [0, 1 / 3, 0], [0, 1 / 3, 1]]),
    )
    occupied = torch.zeros(4**3, dtype=torch.bool)
    occupied[0] = True  # the corner cell [0, 1/4)^3, grown by one cell: [0, 1/2)^3
    inside = vertices_in_cells(occupied, 4, 9)  # vertices at multiples of 1/8
    x = lattice_points(torch.arange(9**3), 9)
    assert torch.equal(inside, (x < 0.5).all(-1))


class AnalyticBall:
    """A source field: density 40 inside the ball |x| < 0.4, 0 outside; the colour's logits a
    degree-2 SH function of the direction whose DC term is 3 x (so it varies in space)."""

    has_radiance = True

    def coeffs(self, x):
        c = torch.zeros(x.shape[0], 9, 3)
        c[:, 0, :] = 3 * x[:, :1]
        c[:, 4, 1] = 0.5  # a view-dependent green
        return c

    def density(self, x):
        return torch.where(x.norm(dim=-1) < 0.4, 40.0, 0.0)

    def radiance(self, x, dirs):
        rgb = torch.sigmoid(eval_sh(2, self.coeffs(x)[:, None], dirs[None]))
        return self.density(x), rgb


def test_bake_keeps_the_field_near_the_ball_with_its_exact_values():
    aabb = torch.tensor([[-1.0] * 3, [1.0] * 3])
    res, scale = 21, 10.0
    flat, density, sh = bake_lattice(AnalyticBall(), res, aabb, False, 2, 32, scale, 0.05)
    x_all = lattice_points(torch.arange(res**3), res) * 2 - 1
    inside = x_all.norm(dim=-1) < 0.4
    # kept: the ball's vertices and their 3 x 3 x 3 neighbours, nothing else
    near = torch.zeros(res**3, dtype=torch.bool)
    near[flat] = True
    grown = torch.nn.functional.max_pool3d(inside.float().view(1, 1, res, res, res), 3, 1, 1)
    assert torch.equal(near, grown.reshape(-1) > 0)
    assert torch.allclose(density[:, 0], torch.where(inside[flat], 4.0, 0.0))
    # SH laid out (M, 3, K) as PlenoxelModel reads it, equal to the source's coefficients
    fitted = sh.view(-1, 3, 9).transpose(1, 2)
    assert torch.allclose(fitted, AnalyticBall().coeffs(x_all[flat]), atol=2e-4)


def test_bake_respects_the_candidates():
    aabb = torch.tensor([[-1.0] * 3, [1.0] * 3])
    res = 11
    x = lattice_points(torch.arange(res**3), res) * 2 - 1
    candidates = x[:, 0] < 0  # half of the lattice
    flat, _, _ = bake_lattice(AnalyticBall(), res, aabb, False, 2, 16, 10.0, 0.05, candidates)
    assert len(flat) > 0 and bool(candidates[flat].all())


def test_an_unbounded_lattice_bakes_only_finite_points():
    """Vertices of an unbounded lattice outside the contraction's ball stand for no point."""
    aabb = torch.tensor([[-1.0] * 3, [1.0] * 3])
    flat, density, sh = bake_lattice(AnalyticBall(), 9, aabb, True, 2, 16, 10.0, 0.05)
    assert len(flat) and torch.isfinite(density).all() and torch.isfinite(sh).all()


def psnr(a, b):
    return -10 * math.log10(((a - b) ** 2).mean().item())


def test_a_baked_ngp_renders_like_the_ngp_and_trains_on(tmp_path):
    torch.manual_seed(0)
    data, info = sphere_scene()
    ngp = NGPModel(SMALL, info)
    for step in range(150):
        train_step(ngp, data, step)
    ngp.eval()
    path = save_model(tmp_path / "model.pt", "ngp", vars(SMALL), ngp)
    cfg = sphere_config(bake_from=str(path))
    model = PlenoxelModel(cfg, info)
    model.bake(data)
    assert model.res == 32 and int(model.level) == 1  # the finest lattice, straight away
    views = range(0, len(data), 3)
    ngp_rgb = [ngp.render(data.cameras[i])["rgb"] for i in views]
    baked = [model.render(data.cameras[i])["rgb"] for i in views]
    # the bake alone renders close to what the ngp renders (this half-trained ngp 150 steps
    # on a 24 px sphere: 20.2 dB, ngp against the photos 25.3 dB, the bake 18.7 dB)
    fidelity = psnr(torch.stack(baked), torch.stack(ngp_rgb))
    assert fidelity > 18, fidelity
    truth = torch.stack([data.images[i] for i in views])
    before = psnr(torch.stack(baked), truth)
    flat = 10 * math.log10(1 / truth.var(dim=(0, 1, 2)).mean().item())  # the mean colour
    assert before > flat + 5, (before, flat)
    # training goes on from the bake (its first step bakes again from the file)
    model = PlenoxelModel(cfg, info)
    for step in range(40):
        train_step(model, data, step)
    after = psnr(torch.stack([model.render(data.cameras[i])["rgb"] for i in views]), truth)
    assert after > before, (before, after)
    # a plenoxel started from nothing is far behind after the same steps
    scratch = PlenoxelModel(sphere_config(), info)
    for step in range(40):
        train_step(scratch, data, step)
    behind = psnr(torch.stack([scratch.render(data.cameras[i])["rgb"] for i in views]), truth)
    assert after > behind + 3, (after, behind)


def test_bake_from_through_the_cli(tmp_path):
    import json

    from tests.conftest import recon_cli, sphere_workspace

    ws = str(sphere_workspace(tmp_path))
    small = ["--set", "log2_table_size=14", "--set", "n_max=128", "--set", "n_levels=8"]
    small += ["--set", "rays_per_batch=256", "--set", "samples_per_batch=0"]
    recon_cli("train", "-w", ws, "--method", "ngp", "--steps", "40", "--eval-every", "1e5", *small)
    before = sorted(p.name for p in (tmp_path / "ws" / "runs").iterdir())

    def train(*args):
        return recon_cli(
            "train", "-w", ws, "--steps", "3", "--eval-every", "1e5", *args, check=False
        )

    wrong_method = train("--method", "3dgs", "--bake-from", "ngp")
    assert wrong_method.returncode != 0 and "plenoxel" in wrong_method.stderr
    missing = train("--method", "plenoxel", "--bake-from", "nope")
    assert missing.returncode == 1 and "run 'nope' does not exist" in missing.stderr
    assert sorted(p.name for p in (tmp_path / "ws" / "runs").iterdir()) == before
    done = train("--method", "plenoxel", "--bake-from", "ngp", "--json")
    assert done.returncode == 0, done.stderr
    run = json.loads((tmp_path / "ws" / "runs" / "ngp-baked" / "run.json").read_text())
    assert run["status"] == "done" and run["config"]["bake_from"].endswith("model.pt")
    # a plenoxel run has no neural field to bake
    again = train("--method", "plenoxel", "--bake-from", "ngp-baked", "--run", "twice")
    assert again.returncode == 1 and "no radiance field" in again.stderr
    assert len(again.stderr.strip().splitlines()) == 1


def test_radiance_is_the_field_the_renderers_evaluate():
    """ngp's and nerf's `radiance` (sigma once, the colour along D directions) against the
    per-sample paths their renders take: ngp's colour MLP on each sample's own direction,
    nerf's `NeRFMLP.forward` with one sample per ray."""
    from recon.fields.encodings import positional_encoding
    from recon.models.nerf import NeRFConfig, NeRFModel

    torch.manual_seed(0)
    _, info = sphere_scene()
    x = torch.rand(50, 3) * 1.2 - 0.6
    dirs = torch.nn.functional.normalize(torch.randn(3, 3), dim=-1)
    ngp = NGPModel(SMALL, info)
    sigma, rgb = ngp.radiance(x, dirs)
    assert sigma.shape == (50,) and rgb.shape == (50, 3, 3)
    ref_sigma, geo = ngp.field.geometry(ngp.to_unit(x))
    torch.testing.assert_close(sigma, ref_sigma)
    for j, d in enumerate(dirs):
        enc = ngp.field.encode_directions(d.expand(50, 3))
        torch.testing.assert_close(rgb[:, j], ngp.field.color(geo, enc))
    nerf = NeRFModel(NeRFConfig(precision="fp32"), info)
    sigma, rgb = nerf.radiance(x, dirs)
    for j, d in enumerate(dirs):
        d_enc = positional_encoding(d.expand(50, 3), nerf.cfg.dir_bands)
        ref_sigma, ref_rgb = nerf.fine(nerf.encode_points(x), d_enc)
        torch.testing.assert_close(sigma, ref_sigma)
        torch.testing.assert_close(rgb[:, j], ref_rgb, atol=1e-6, rtol=1e-5)
