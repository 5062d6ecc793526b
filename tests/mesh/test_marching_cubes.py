import math

import numpy as np
import pytest
import torch

from recon.mesh.marching_cubes import (
    choose_density_threshold,
    evaluate_grid,
    extract_density_mesh,
    grid_shape,
    mesh_from_grid,
    soft_field_threshold,
)

# An off-centre ellipsoid in a non-cubic box: a swapped axis or a wrong origin shows up at once.
AABB = np.array([[-0.3, -1.0, 0.2], [1.5, 0.8, 2.0]])
CENTER = np.array([0.6, -0.1, 1.1])
RADII = np.array([0.7, 0.5, 0.4])


def _ellipsoid_level(p: torch.Tensor, radii=RADII) -> torch.Tensor:
    """q(p) = |(p - c) / radii|, 1 on the ellipsoid."""
    c = torch.as_tensor(CENTER, dtype=p.dtype)
    r = torch.as_tensor(radii, dtype=p.dtype)
    return ((p - c) / r).norm(dim=-1)


def _step_sphere(p):  # opaque inside, empty outside: the worst case for vertex placement
    return 50.0 * (_ellipsoid_level(p, radii=[0.5, 0.5, 0.5]) < 1).to(p.dtype)


def _smooth_sphere(p):  # 10 at radius 0.5, decreasing outward
    return 20.0 * torch.exp(-math.log(2) * _ellipsoid_level(p, radii=[0.5, 0.5, 0.5]) ** 4)


def _smooth_density(p):  # the ellipsoid, 10 on its surface
    return 20.0 * torch.exp(-math.log(2) * _ellipsoid_level(p) ** 4)


def _ellipsoid_distance(vertices: np.ndarray) -> np.ndarray:
    """First-order distance |q - 1| / |grad q| to the ellipsoid (error O(d^2 curvature))."""
    x = (vertices - CENTER) / RADII
    q = np.linalg.norm(x, axis=1)
    grad = np.linalg.norm(x / RADII, axis=1) / q
    return np.abs(q - 1) / grad


def test_threshold_worked_example():
    h = 2 / 255
    sigma = choose_density_threshold(h)
    assert sigma == pytest.approx(math.log(2) * 127.5)
    assert 1 - math.exp(-sigma * h) == pytest.approx(0.5)  # one voxel of it is half opaque
    assert choose_density_threshold(0.1, opacity=0.9) == pytest.approx(math.log(10) / 0.1)


def test_soft_field_threshold_worked_example():
    assert soft_field_threshold(150.0, np.array([4.0, 9.0, 40.0])) == 9.0  # softer than a voxel
    assert (
        soft_field_threshold(150.0, np.array([400.0, 900.0])) == 150.0
    )  # sharper: the voxel level
    assert soft_field_threshold(150.0, np.array([np.nan])) == 150.0  # no rendered surface


def test_soft_field_threshold_meshes_a_blurry_sphere():
    """A sphere blurred over ~10 voxels never reaches ln 2 / h; the level at the surface does."""

    def blurry(p):
        return 20.0 * torch.sigmoid((0.6 - p.norm(dim=-1)) / 0.05)

    aabb = np.array([[-1.0] * 3, [1.0] * 3])
    _, h = grid_shape(aabb, 64)
    assert len(extract_density_mesh(blurry, aabb, 64, choose_density_threshold(h)).faces) == 0
    surface = blurry(torch.tensor([[0.6, 0.0, 0.0], [0.0, 0.61, 0.0], [0.0, 0.0, -0.59]])).numpy()
    level = soft_field_threshold(choose_density_threshold(h), surface)
    radius = np.linalg.norm(extract_density_mesh(blurry, aabb, 64, level).vertices, axis=1)
    assert np.abs(radius - 0.6).max() < 0.02


def test_grid_shape_is_isotropic():
    shape, h = grid_shape(AABB, 37)
    assert h == pytest.approx(1.8 / 36)
    assert shape == (37, 37, 37)
    shape, h = grid_shape([[0, 0, 0], [2.0, 1.0, 0.5]], 41)
    assert h == pytest.approx(0.05) and shape == (41, 21, 11)


def test_chunked_grid_matches_dense_meshgrid():
    shape, h = grid_shape(AABB, 13)
    got = evaluate_grid(_smooth_density, AABB[0], h, shape, chunk=400)  # 2 x-slices a batch
    axes = [AABB[0, a] + h * np.arange(shape[a]) for a in range(3)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    expected = _smooth_density(torch.from_numpy(points)).numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)


# The step field at level 25 puts each vertex at the midpoint of a crossing edge: within h/2.
@pytest.mark.parametrize(
    "density, level, tol_voxels", [(_step_sphere, 25.0, 0.5), (_smooth_sphere, 10.0, 0.05)]
)
def test_sphere_vertices_within_half_a_voxel_and_outward(density, level, tol_voxels):
    mesh = extract_density_mesh(density, AABB, resolution=48, threshold=level, chunk=5000)
    _, h = grid_shape(AABB, 48)
    assert len(mesh.faces) > 1000
    radius = np.linalg.norm(mesh.vertices - CENTER, axis=1)
    assert np.abs(radius - 0.5).max() <= tol_voxels * h + 1e-6
    assert mesh.is_watertight and mesh.euler_number == 2
    # outward: every face normal points away from the centre
    assert (np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles_center - CENTER) > 0).all()
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * 0.5**3, rel=0.03)


def test_ellipsoid_axes_and_origin_in_box_frame():
    mesh = extract_density_mesh(_smooth_density, AABB, resolution=48, threshold=10.0)
    _, h = grid_shape(AABB, 48)
    assert _ellipsoid_distance(mesh.vertices).max() < 0.1 * h  # a swapped axis is off by ~0.2
    np.testing.assert_allclose(mesh.bounds, [CENTER - RADII, CENTER + RADII], atol=0.1 * h)
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * RADII.prod(), rel=0.01)


def test_vertex_colors_follow_color_fn():
    def color_fn(p):
        return (p - torch.as_tensor(AABB[0], dtype=p.dtype)) / 1.8

    mesh = extract_density_mesh(_smooth_density, AABB, 24, 10.0, color_fn=color_fn)
    expected = np.clip((mesh.vertices - AABB[0]) / 1.8, 0, 1) * 255
    np.testing.assert_allclose(mesh.visual.vertex_colors[:, :3], expected, atol=0.51)


def test_no_crossing_gives_empty_mesh():
    mesh = extract_density_mesh(lambda p: torch.zeros(len(p)), AABB, 8, 1.0)
    assert len(mesh.faces) == 0 and len(mesh.vertices) == 0


def test_valid_cubes_drop_exactly_the_cubes_with_missing_data():
    shape, h = grid_shape(AABB, 20)
    values = evaluate_grid(_smooth_density, AABB[0], h, shape)
    full = mesh_from_grid(values, AABB[0], h, 10.0)
    valid = np.ones(tuple(s - 1 for s in shape), bool)
    valid[:, :, : shape[2] // 2] = False  # drop the lower half in z
    half = mesh_from_grid(values, AABB[0], h, 10.0, valid_cubes=valid)
    z_cut = AABB[0, 2] + h * (shape[2] // 2)
    centers_full = full.triangles_center
    assert (half.triangles_center[:, 2] >= z_cut - 1e-9).all()
    assert len(half.faces) == int((centers_full[:, 2] > z_cut).sum())
