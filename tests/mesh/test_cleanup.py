import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from recon.mesh.cleanup import (
    in_view,
    keep_largest_components,
    keep_seen_components,
    keep_visible_faces,
    mesh_stats,
    remove_small_components,
    transform_mesh,
    visible_faces,
    write_mesh,
)


def _scene_with_floaters() -> trimesh.Trimesh:
    """A big sphere (1280 faces), a medium one (320) and a tiny tetrahedron (4), coloured."""
    big = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    medium = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    medium.apply_translation([3, 0, 0])
    tiny = trimesh.creation.icosphere(subdivisions=0, radius=0.05)
    tiny.apply_translation([0, 3, 0])
    tiny = trimesh.Trimesh(tiny.vertices, tiny.faces[:4])
    mesh = trimesh.util.concatenate([tiny, big, medium])  # the big one is not first
    mesh.visual.vertex_colors = np.tile([10, 20, 30, 255], (len(mesh.vertices), 1))
    return mesh


def test_stats_counts_components():
    stats = mesh_stats(_scene_with_floaters())
    assert stats["components"] == 3 and stats["faces"] == 1280 + 320 + 4
    assert not stats["watertight"]  # the open tetrahedron fragment


def test_keep_largest_components():
    mesh = _scene_with_floaters()
    one = keep_largest_components(mesh, 1)
    assert len(one.faces) == 1280 and one.is_watertight
    assert np.linalg.norm(one.vertices, axis=1).max() == pytest.approx(1.0)
    assert (one.visual.vertex_colors[:, :3] == [10, 20, 30]).all()
    assert len(keep_largest_components(mesh, 2).faces) == 1600


@pytest.mark.parametrize("fraction, faces", [(0.001, 1604), (0.01, 1600), (0.5, 1280), (0.9, 1280)])
def test_remove_small_components(fraction, faces):
    assert len(remove_small_components(_scene_with_floaters(), fraction).faces) == faces


def test_transform_worked_example_and_orientation():
    mesh = trimesh.creation.icosphere(subdivisions=2)
    R = Rotation.from_euler("xyz", [0.3, -0.7, 1.1]).as_matrix()
    out = transform_mesh(mesh, 2.0, R, np.array([1.0, -2.0, 0.5]))
    expected = 2.0 * mesh.vertices @ R.T + [1.0, -2.0, 0.5]
    np.testing.assert_allclose(out.vertices, expected, atol=1e-12)
    point = transform_mesh(trimesh.Trimesh([[1.0, 1, 1]], []), 2.0, np.eye(3), [1.0, 0, 0])
    np.testing.assert_allclose(point.vertices, [[3.0, 2, 2]])
    assert out.volume == pytest.approx(8 * mesh.volume)  # positive: still outward
    with pytest.raises(ValueError):
        transform_mesh(mesh, 1.0, np.diag([1.0, 1, -1]), np.zeros(3))


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".glb"])
def test_write_roundtrip(tmp_path, suffix):
    mesh = keep_largest_components(_scene_with_floaters())
    path = write_mesh(mesh, tmp_path / "out" / f"mesh{suffix}")
    loaded = trimesh.load(path, force="mesh", process=False)
    assert len(loaded.faces) == len(mesh.faces)
    np.testing.assert_allclose(
        np.sort(loaded.vertices, axis=0), np.sort(mesh.vertices, axis=0), atol=1e-5
    )
    assert (loaded.visual.vertex_colors[:, :3] == [10, 20, 30]).all()
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temp file left


def test_write_rejects_unknown_format(tmp_path):
    with pytest.raises(ValueError):
        write_mesh(trimesh.creation.box(), tmp_path / "mesh.stl")


def _camera_at_origin_looking_down_z(size=(100, 80)):
    K = np.array([[50.0, 0, size[0] / 2], [0, 50.0, size[1] / 2], [0, 0, 1]])
    return K, np.eye(4), np.array(size)


def test_in_view_worked_example():
    K, cam_from_world, size = _camera_at_origin_looking_down_z()
    points = np.array([[0, 0, 1.0], [0, 0, -1.0], [0.99, 0, 1.0], [1.01, 0, 1.0], [0, 0.79, 1]])
    # u = 50 x / z + 50: x = 0.99 -> 99.5 (inside [0, 100)), x = 1.01 -> 100.5 (outside);
    # v = 50 y / z + 40: y = 0.79 -> 79.5 (inside [0, 80)); behind the camera is never in view
    assert in_view(points, K, cam_from_world, size).tolist() == [True, False, True, False, True]


def test_keep_seen_components_drops_what_no_camera_sees():
    mesh = _scene_with_floaters()  # spheres at (0, 0, 0), (3, 0, 0) and the tiny one at (0, 3, 0)
    mesh.apply_translation([0, 0, 5])
    K, cam_from_world, size = _camera_at_origin_looking_down_z()  # sees |x|, |y| < ~4 at z = 5
    seen = keep_seen_components(mesh, K[None], cam_from_world[None], size[None])
    assert mesh_stats(seen)["components"] == 3
    behind = cam_from_world.copy()
    behind[:3, :3] = np.diag([-1.0, 1.0, -1.0])  # turned around: sees nothing
    assert len(keep_seen_components(mesh, K[None], behind[None], size[None]).faces) == 0
    narrow = np.array([[20, 16]])  # a small image: only the big sphere projects inside it
    kept = keep_seen_components(
        mesh, np.array([[[50.0, 0, 10], [0, 50, 8], [0, 0, 1]]]), cam_from_world[None], narrow
    )
    assert mesh_stats(kept)["components"] == 1 and len(kept.faces) == 1280


def _slab(z_front, z_back, half=0.5):
    """Two parallel squares (a shell's front and back sheets) facing a camera at the origin."""
    v = []
    for z in (z_front, z_back):
        v += [[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]]
    f = [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]]
    return trimesh.Trimesh(np.array(v, float), np.array(f), process=False)


def test_visible_faces_drop_the_back_sheet_of_a_shell_and_keep_what_a_camera_sees():
    K = np.array([[[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]]])
    eye = np.eye(4)[None]
    slab = _slab(2.0, 2.1)
    seen = visible_faces(slab, K, eye, np.array([[100, 100]]), tolerance=0.05)
    assert seen.tolist() == [True, True, False, False]
    # within the tolerance both sheets count as the surface
    assert visible_faces(slab, K, eye, np.array([[100, 100]]), tolerance=0.2).all()
    # a second camera behind the slab, looking back at it (turned 180 deg about y), sees the back
    behind = np.eye(4)
    behind[:3, :3] = np.diag([-1.0, 1.0, -1.0])
    behind[:3, 3] = [0.0, 0.0, 4.1]  # x_cam = R x + t: the back sheet at depth 2, the front 2.1
    both = visible_faces(
        slab, np.r_[K, K], np.r_[eye, behind[None]], np.array([[100, 100]] * 2), 0.05
    )
    assert both.all()
    kept = keep_visible_faces(slab, K, eye, np.array([[100, 100]]), tolerance=0.05)
    assert len(kept.faces) == 2 and len(kept.vertices) == 4
    assert np.allclose(kept.vertices[:, 2], 2.0)
