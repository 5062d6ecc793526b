import math
from unittest.mock import patch

import pytest
import torch

from recon.cameras import camera_rays
from recon.fields.voxel_kernels import corners
from recon.fields.voxels import SparseVoxelGrid, linked_corners_torch, trilinear_corners
from recon.models.plenoxel import PlenoxelConfig, PlenoxelModel
from recon.models.raymarch import render_image
from recon.volrend import ray_aabb_intersect
from recon.volrend.occupancy import cell_points
from tests.conftest import sphere_scene, train_step, trainer_of


def test_trilinear_weights_sum_to_one_and_interpolate_linear_fields():
    torch.manual_seed(0)
    res = 5
    x = torch.rand(100, 3, dtype=torch.float64)
    idx, w = trilinear_corners(x, res)
    assert torch.allclose(w.sum(-1), torch.ones(100, dtype=torch.float64))
    # a linear function of the vertex coordinates is reproduced exactly
    flat = torch.arange(res**3)
    ijk = torch.stack([flat % res, (flat // res) % res, flat // res**2], -1).double() / (res - 1)
    f = ijk @ torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    assert torch.allclose(
        (f[idx] * w).sum(-1), x @ torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    )
    # exactly on the far faces and corners
    corner = torch.ones(1, 3, dtype=torch.float64)
    assert torch.allclose(
        (f[trilinear_corners(corner, res)[0]] * trilinear_corners(corner, res)[1]).sum(),
        torch.tensor(-0.5, dtype=torch.float64),
    )


def test_grid_prune_and_upsample_preserve_the_field():
    grid = SparseVoxelGrid(9, {"density": 1}, {"density": 0.0})
    with torch.no_grad():
        flat = torch.arange(9**3)
        ijk = torch.stack([flat % 9, (flat // 9) % 9, flat // 81], -1).float() / 8
        grid.data["density"][:, 0] = (ijk - 0.5).norm(dim=-1).lt(0.3).float() * 2.0 + ijk[:, 0]
    x = torch.rand(500, 3)
    before = grid.query(x)["density"]
    grid.upsample(17, lambda occ: occ)
    after = grid.query(x)["density"]
    # a trilinear field resampled on a 2x finer lattice is unchanged up to interpolation of the step
    assert (after - before).abs().median() < 0.05
    keep = grid.data["density"][:, 0] > 0.5
    grid.prune(keep)
    assert grid.num_rows == int(keep.sum())
    _, b = grid.neighbour_pairs(torch.arange(grid.num_rows))
    assert torch.all(grid.links[grid.coords[b]] == b)


def sphere_config(**overrides):
    """A small lattice for `sphere_scene` (16^3, then 32^3 from step 60)."""
    return PlenoxelConfig(
        **{
            "resolutions": (16, 32),
            "upsample_steps": (60,),
            "rays_per_batch": 1024,
            "lr_decay_steps": 1000,
            "samples_per_batch": 1 << 15,
            "occupancy_res": 16,
            "chunk": 4096,
            **overrides,
        }
    )


@pytest.mark.slow
def test_plenoxel_learns_a_sphere():
    torch.manual_seed(0)
    data, info = sphere_scene()
    cfg = sphere_config()
    model = PlenoxelModel(cfg, info)
    baseline = 10 * math.log10(1 / data.images.var(dim=(0, 1, 2)).mean().item())
    losses = [train_step(model, data, s)["loss"] for s in range(120)]
    assert losses[-1] < 0.5 * losses[0]
    out = model.render(data.cameras[0])
    assert out["rgb"].shape == (24, 24, 3) and torch.isfinite(out["depth"]).all()
    psnr = -10 * math.log10(((out["rgb"] - data.images[0]) ** 2).mean().item())
    assert psnr > baseline + 8, (psnr, baseline)
    assert model.res == 32
    # the state round-trips into a fresh model (grids change size during training)
    fresh = PlenoxelModel(cfg, info)
    fresh.load_state_dict(model.state_dict())
    trainer_of(fresh).load_state_dict(trainer_of(model).state_dict())
    assert torch.allclose(fresh.render(data.cameras[0])["rgb"], out["rgb"], atol=1e-6)


def trained_sphere(steps=120, **overrides):
    torch.manual_seed(0)
    data, info = sphere_scene()
    model = PlenoxelModel(sphere_config(**overrides), info)
    for s in range(steps):
        train_step(model, data, s)
    return model, data


def test_vertex_weights_are_blend_weights_times_trilinear_shares():
    """One ray's weights: each linked vertex gets at most the largest sample weight of the ray,
    and the per-sample shares summed over a sample's 8 corners give the sample weights back."""
    model, data = trained_sphere(steps=80)
    rays = data.rays()
    o, d = rays["origins"][:300], rays["directions"][:300]
    best = model.vertex_weights(o, d)
    out = model.render_rays(o, d, jitter=False)
    assert best.shape == (model.grid.num_rows,) and (best >= 0).all()
    assert float(best.max()) <= float(out["weights"].detach().max()) + 1e-6
    assert float(best.max()) > 0.05  # the sphere's surface is seen


def test_linked_corners_torch_twin_matches_the_numba_kernel():
    """`voxels.linked_corners_torch` (the path off the CPU) against `voxel_kernels.corners`:
    the same rows (pruned vertices -1) and weights, at points inside, on faces and corners, and
    outside the cube (clamped)."""
    g = torch.Generator().manual_seed(0)
    grid = SparseVoxelGrid(9, {"density": 1}, {"density": 0.0})
    grid.prune(torch.rand(9**3, generator=g) > 0.3)
    for dtype in (torch.float32, torch.float64):
        x = torch.rand(400, 3, generator=g, dtype=dtype) * 1.2 - 0.1
        x[:8] = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        x[8] = 0.5
        rows, w = corners(x, grid.res, grid.links)
        rows_t, w_t = linked_corners_torch(x, grid.res, grid.links)
        assert (rows == -1).any() and torch.equal(rows, rows_t)
        torch.testing.assert_close(w, w_t, rtol=0, atol=1e-6 if dtype == torch.float32 else 0)


def test_vertex_weights_off_the_cpu_kernels_match(monkeypatch):
    """The torch path of `vertex_weights` (a GPU's: no sample goes to the host) gives what the
    numba CPU path gives."""
    from recon import devices

    model, data = trained_sphere(steps=40)
    rays = data.rays()
    o, d = rays["origins"][::3], rays["directions"][::3]
    cpu = model.vertex_weights(o, d)
    monkeypatch.setattr(devices, "uses_cpu_kernels", lambda t: False)
    twin = model.vertex_weights(o, d)
    assert float(cpu.max()) > 0.05
    torch.testing.assert_close(twin, cpu, rtol=0, atol=1e-5)


def test_finish_prunes_unseen_vertices_and_keeps_the_renders():
    """The inside of the sphere and space no ray reaches go; every training view renders the
    same within a small tolerance (what is pruned took weight < 0.001 on every ray traced).
    (lego-200 at 256^3: 3.65 M -> 1.93 M vertices, test PSNR -0.006 dB.)"""
    model, data = trained_sphere(finish_ray_stride=1, upsample_prune_unseen=False)
    before = [model.render(data.cameras[i])["rgb"] for i in range(len(data))]
    rows = model.grid.num_rows
    stats = model.finish(data)
    assert stats["finish_rows_before"] == rows
    assert stats["finish_rows_after"] == model.grid.num_rows < 0.8 * rows
    for i in range(len(data)):
        after = model.render(data.cameras[i])["rgb"]
        assert (after - before[i]).abs().mean() < 2e-3
    off = PlenoxelModel(
        model.cfg.__class__(**{**model.cfg.__dict__, "finish_weight": 0.0}), model.scene
    )
    assert off.finish(data) == {}


def test_file_state_round_trip():
    """model.pt's small form (vertex bitmask, float16 density, int8 SH, deflated) loads back to
    the same lattice (rows in ascending vertex order), density to float16 rounding, SH to half
    a quantisation step, and renders within 5e-3 of the model it came from; the state_dict of a
    checkpoint still loads exactly."""
    model, data = trained_sphere(steps=80)
    state = model.file_state()
    assert not {"grid.links", "grid.coords", "grid.data.sh"} & set(state)
    fresh = PlenoxelModel(model.cfg, model.scene)
    fresh.load_state_dict(state)
    order = torch.argsort(model.grid.coords)
    assert fresh.res == model.res and torch.equal(fresh.grid.coords, model.grid.coords[order])
    density = model.grid.data["density"].detach()[order]
    assert torch.equal(fresh.grid.data["density"], density.half().float())
    sh = model.grid.data["sh"].detach()[order]
    step = sh.abs().amax(dim=0) / 127
    assert ((fresh.grid.data["sh"] - sh).abs() <= step / 2 + 1e-7).all()
    for i in (0, 3):
        a, b = model.render(data.cameras[i])["rgb"], fresh.render(data.cameras[i])["rgb"]
        assert (a - b).abs().max() < 5e-3
    exact = PlenoxelModel(model.cfg, model.scene)
    exact.load_state_dict(model.state_dict())
    assert torch.equal(exact.grid.data["sh"], model.grid.data["sh"])


def test_numba_query_matches_torch_twin_values_and_gradients():
    torch.manual_seed(1)
    grid = SparseVoxelGrid(7, {"density": 1, "sh": 5}, {"density": 0.0})
    with torch.no_grad():
        for p in grid.data.values():
            p.normal_()
    grid.prune(torch.rand(grid.num_rows) > 0.3)  # some vertices pruned: they count as zero
    x = torch.cat(
        [
            torch.rand(300, 3),
            torch.tensor([[0.0, 0, 0], [1, 1, 1], [0.5, 1.0, 0.0], [1.2, -0.1, 0.5]]),
        ]
    )
    fast = grid.query(x)
    ref = grid.query_reference(x)
    for name in grid.data:
        assert torch.allclose(fast[name], ref[name], atol=1e-6)
    g = {n: torch.randn_like(v) for n, v in fast.items()}
    grads_fast = torch.autograd.grad(
        [(fast[n] * g[n]).sum() for n in fast], list(grid.data.values())
    )
    ref = grid.query_reference(x)
    grads_ref = torch.autograd.grad([(ref[n] * g[n]).sum() for n in ref], list(grid.data.values()))
    for a, b in zip(grads_fast, grads_ref):
        assert torch.allclose(a, b, atol=1e-5)


def test_one_pass_march_keeps_the_two_stage_samples():
    """`kept_samples` (numba: march, density and termination in one pass, with or without the
    live-cell test) gives the samples of marching everything and then terminating, with and
    without jitter."""
    model, data = trained_sphere(steps=80)
    rays = data.rays()
    o, d = rays["origins"][::7], rays["directions"][::7]
    t_min, t_max, cone = model._ray_range(o, d)
    for u in (None, torch.rand(o.shape[0], generator=torch.Generator().manual_seed(3))):
        ri, t0, t1 = model.kept_samples(o, d, u)
        ri2, s0, s1 = model._march_then_terminate(o, d, t_min, t_max, cone, u)
        assert ri.numel() > 1000 and torch.equal(ri, ri2)
        assert torch.allclose(t0, s0) and torch.allclose(t1, s1)


def test_live_cells_are_the_cells_with_a_positive_vertex():
    """A 4^3 lattice with one positive vertex (1, 2, 3): live are the 8 cells around it (those
    with i in {0, 1}, j in {1, 2}, k in {2}; k = 3 is past the last cell)."""
    model, _ = trained_sphere(steps=0)
    r = 4
    coords = torch.arange(r**3)
    density = torch.full((r**3, 1), -1.0)
    density[1 + r * (2 + r * 3)] = 0.5
    sh = torch.zeros(r**3, model.grid.data["sh"].shape[1])
    model.grid.set_rows(coords, {"density": density, "sh": sh}, r)
    model._density_changed()
    live = model.live_cells().view(r - 1, r - 1, r - 1)  # (k, j, i)
    expected = torch.zeros_like(live)
    expected[2, 1:3, 0:2] = True
    assert torch.equal(live, expected)


def test_one_pass_render_matches_the_sample_path_after_more_training():
    """`render` on the CPU (`render_lattice`: no sample stored, rays in `tile_order`) against
    `render_rays` chunk by chunk: the same opacity and (where something is hit) depth within
    float32 rounding, also after the density changed under a cached `live_cells` (two more
    training steps); the same rgb within rounding with the SH evaluated along each ray, and
    within 2e-3 with it evaluated per vertex as seen from the camera centre (`render`'s way)."""
    model, data = trained_sphere(steps=80)
    for extra in (0, 2):
        for s in range(80, 80 + extra):
            train_step(model, data, s)
        for i in (0, 3):
            fast = model.render(data.cameras[i])
            slow = render_image(model._render_chunk, data.cameras[i].to("cpu"), model.cfg.chunk)
            assert (fast["acc"] - slow["acc"]).abs().max() < 1e-4
            hit = slow["acc"] > 0.1  # depth = expected t / acc: compared where it is defined
            assert (fast["depth"] - slow["depth"])[hit].abs().max() < 1e-4 * slow["depth"].max()
            assert hit.sum() > 20
            error = (fast["rgb"] - slow["rgb"]).abs()
            assert error.max() < 2e-3 and error.mean() < 1e-4
            origins, dirs, _ = camera_rays(data.cameras[i], 0)
            per_ray, _, _ = model._render_fused(origins.reshape(-1, 3), dirs.reshape(-1, 3))
            assert (per_ray - slow["rgb"].reshape(-1, 3)).abs().max() < 1e-4


def test_lean_preset_stores_degree_one_sh_and_renders_like_the_sample_path():
    from recon.models.registry import method_spec

    lean = method_spec("plenoxel").presets["lean"]
    model, data = trained_sphere(steps=60, **lean)
    assert model.grid.data["sh"].shape[1] == 3 * 4  # 4 bases of degree <= 1 per channel
    fast = model.render(data.cameras[0])
    slow = render_image(model._render_chunk, data.cameras[0].to("cpu"), model.cfg.chunk)
    assert (fast["rgb"] - slow["rgb"]).abs().max() < 2e-3  # colour per vertex: see above
    assert (fast["acc"] > 0.1).sum() > 20


def test_upsampling_keeps_only_what_the_training_rays_see():
    """With upsample_prune_unseen the finer lattice (from step 60) holds far fewer rows than
    without, and the two models trained the same way render the training views alike."""
    on, data = trained_sphere(steps=61, finish_ray_stride=1)
    off, _ = trained_sphere(steps=61, finish_ray_stride=1, upsample_prune_unseen=False)
    assert on.res == off.res == 32 and on.grid.num_rows < 0.8 * off.grid.num_rows
    for i in range(0, len(data), 3):
        a, b = on.render(data.cameras[i])["rgb"], off.render(data.cameras[i])["rgb"]
        assert (a - b).abs().mean() < 5e-3


def test_one_pass_paths_match_the_sample_paths_on_an_unbounded_scene():
    """The same twins with the contraction and cone-growing steps of an unbounded capture (the
    sphere's cameras, far plane 6): kept samples equal, renders within float32 rounding."""
    import dataclasses

    torch.manual_seed(0)
    data, info = sphere_scene()
    info = dataclasses.replace(info, unbounded=True, far=6.0)
    model = PlenoxelModel(sphere_config(), info)
    for s in range(40):
        train_step(model, data, s)
    assert assert_march_twins(model, data, stride=5, jitter=False) > 0
    assert_render_twin(model, data.cameras[2], rgb_tolerance=1e-4)  # colour along each ray


def test_pixel_footprint_worked_example():
    from recon.cameras import Cameras
    from recon.models.plenoxel import pixel_footprint

    # Blender lego at 200 px: f = 100 / tan(0.6911 / 2) = 277.87 px, cameras 4.03 from the centre
    K = torch.tensor([[277.87, 0, 100], [0, 277.87, 100], [0, 0, 1]])
    cfw = torch.eye(4).repeat(3, 1, 1)
    cfw[:, 2, 3] = torch.tensor([4.03, 4.03, 8.06])  # the centre 4.03, 4.03, 8.06 ahead
    cams = Cameras(K.expand(3, 3, 3), cfw, torch.full((3,), 200), torch.full((3,), 200))
    assert abs(pixel_footprint(cams, torch.zeros(3)) - 4.03 / 277.87) < 1e-6  # the median


def test_finest_lattice_worked_examples():
    from recon.models.plenoxel import finest_lattice, lattice_schedule

    assert finest_lattice(0.588, 0.003165, False) == 192  # lego-200: 185.8 across -> 192
    assert finest_lattice(3.0, 0.0145, False) == 192  # 206.9 -> 192
    assert finest_lattice(3.0, 0.025, False) == 128  # 120 -> 128
    assert finest_lattice(3.0, 0.03, True) == 192  # the box is the lattice's middle half: 200
    assert finest_lattice(3.0, 0.0145, True) == 256  # 413.8, at most 256
    assert finest_lattice(3.0, 0.0145 / 2, False) == 256  # twice the pixels (lego-400): 256
    assert finest_lattice(3.0, 0.5, False) == 64  # at least 64
    assert lattice_schedule((32, 64, 128, 0), 192) == (32, 64, 128, 192)
    assert lattice_schedule((32, 64, 128, 0), 96) == (32, 64, 96)
    assert lattice_schedule((32, 64, 128, 256), 96) == (32, 64, 128, 256)  # no 0: as given


def test_the_finest_lattice_is_sized_once_and_saved():
    import pytest

    data, info = sphere_scene()
    model = PlenoxelModel(sphere_config(resolutions=(16, 0)), info)
    assert model.lattice_sizes() == (16, 0)  # nothing decided before the cameras are seen
    note = model.plan_note(data)
    sizes = model.lattice_sizes()
    assert sizes[0] == 16 and sizes[-1] >= 64 and sizes[-1] % 32 == 0
    assert "sized to the training photos" in note and str(sizes[-1]) in note
    for step in range(62):
        train_step(model, data, step)
    assert model.res == sizes[-1]
    fresh = PlenoxelModel(sphere_config(resolutions=(16, 0)), info)
    fresh.load_state_dict(model.state_dict())
    assert fresh.lattice_sizes() == sizes and fresh.res == sizes[-1]
    assert "as configured" in PlenoxelModel(sphere_config(), info).plan_note(data)
    for bad in ((0, 32), (16, 0, 64), ()):
        with pytest.raises(ValueError, match="only the last"):
            PlenoxelModel(sphere_config(resolutions=bad), info)


def test_the_march_range_shrunk_to_the_occupied_box_keeps_every_sample():
    """`_within_occupied`: the same kept samples (to rounding) and renders as marching the
    whole box, with and without jitter; rays that miss the occupied box march nothing."""
    model, data = trained_sphere(steps=80)
    occ = model.occupancy  # keep the cells near the sphere (|x| < 0.6 in the +-0.7 box)
    centres = cell_points(torch.arange(occ.resolution**3), occ.resolution, torch.full((1, 3), 0.5))
    occ.occupied &= ((centres * 2 - 1) * 0.7).norm(dim=-1) < 0.6
    box = occ.occupied_box()
    assert box is not None and (box[0] > 0.05).all() and (box[1] < 0.95).all()
    rays = data.rays()
    o, d = rays["origins"][::5], rays["directions"][::5]
    shrunk = model._ray_range(o, d)[:2]
    whole = ray_aabb_intersect(o, d, model.aabb)[:2]
    assert (shrunk[1] - shrunk[0]).sum() < 0.8 * (whole[1] - whole[0].clamp_min(0.05)).sum()
    for u in (None, torch.rand(o.shape[0], generator=torch.Generator().manual_seed(3))):
        ri, t0, t1 = model.kept_samples(o, d, u)
        with patch.object(PlenoxelModel, "_within_occupied", lambda self, o, d, a, b: (a, b)):
            ri2, s0, s1 = model.kept_samples(o, d, u)
            whole_render = model.render(data.cameras[2])
        assert ri.numel() > 1000 and torch.equal(ri, ri2)
        assert torch.allclose(t0, s0, atol=1e-5) and torch.allclose(t1, s1, atol=1e-5)
    out = model.render(data.cameras[2])
    assert (out["rgb"] - whole_render["rgb"]).abs().max() < 1e-4
    # nothing occupied: no ray marches at all
    model.occupancy.occupied.fill_(False)
    assert model.occupancy.occupied_box() is None
    t_min, t_max, _ = model._ray_range(o, d)
    assert torch.equal(t_min, t_max)


@pytest.mark.parametrize("cone_angle", [0.0, 1 / 64])
def test_empty_space_skipping_keeps_every_sample(cone_angle):
    """With occupied cells only around a small ball (most coarse cells empty, so the march
    jumps over whole coarse cells, occupancy cells and dead lattice cells), the one-pass march
    keeps exactly the samples of marching every step (the two-stage twin), with and without
    jitter, and the one-pass render matches the sample path."""
    model, data = trained_sphere(steps=80, cone_angle=cone_angle)
    occ = model.occupancy
    centres = cell_points(torch.arange(occ.resolution**3), occ.resolution, torch.full((1, 3), 0.5))
    occ.occupied &= ((centres * 2 - 1) * 0.7 - 0.1).norm(dim=-1) < 0.35
    coarse, _ = occ.coarse(4)
    assert 0 < coarse.sum() < 0.5 * coarse.numel()
    assert assert_march_twins(model, data, stride=3, jitter=True) == cone_angle
    assert_render_twin(model, data.cameras[2], rgb_tolerance=2e-3)  # colour per vertex


def assert_march_twins(model, data, stride: int, jitter: bool) -> float:
    """`kept_samples` (one pass, skipping empty space) keeps exactly the samples of
    `_march_then_terminate` (every step, then termination) on every stride-th training ray,
    without jitter and, if asked, with it (at least 500 samples). Returns the cone angle."""
    rays = data.rays()
    o, d = rays["origins"][::stride], rays["directions"][::stride]
    t_min, t_max, cone = model._ray_range(o, d)
    jitters = [None]
    if jitter:
        jitters.append(torch.rand(o.shape[0], generator=torch.Generator().manual_seed(3)))
    for u in jitters:
        ri, t0, t1 = model.kept_samples(o, d, u)
        ri2, s0, s1 = model._march_then_terminate(o, d, t_min, t_max, cone, u)
        assert ri.numel() > 500 and torch.equal(ri, ri2)
        assert torch.allclose(t0, s0) and torch.allclose(t1, s1)
    return cone


def assert_render_twin(model, camera, rgb_tolerance: float) -> None:
    """`render` (one numba pass) against `render_rays` chunk by chunk: opacity within float32
    rounding, rgb within rgb_tolerance."""
    fast = model.render(camera)
    slow = render_image(model._render_chunk, camera, model.cfg.chunk)
    assert (fast["acc"] - slow["acc"]).abs().max() < 1e-4
    assert (fast["rgb"] - slow["rgb"]).abs().max() < rgb_tolerance
