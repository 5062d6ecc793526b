"""The mesh preview rasterizer: a worked example (a square facing the camera), occlusion, the
head-light shade of a tilted face, and a brute-force twin (one ray-triangle test per pixel)."""

import math

import numpy as np
import trimesh

from recon.mesh.preview import AMBIENT, BACKGROUND, preview_views, shade_mesh

K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
EYE = np.eye(4)


def square(z, half=0.5):
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def test_a_square_facing_the_camera():
    """Side 1 at depth 2, f = 100: it spans u, v in [25, 75], so the pixels whose centres lie
    inside are 25..74: 50 x 50 at depth 2. Each half is lit along the ray to its centroid
    (+-1/6, -+1/6, 2): cos = 2 / sqrt(4 + 2/36), brightness 0.8 x 255 (0.15 + 0.85 cos) = 203."""
    v, f = square(2.0)
    image, depth = shade_mesh(v, f, K, EYE, 100, 100)
    covered = np.isfinite(depth)
    assert covered.sum() == 2500 and covered[25:75, 25:75].all()
    assert np.allclose(depth[covered], 2.0)
    cos = 2 / math.sqrt(4 + 2 / 36)
    assert round(204 * (AMBIENT + (1 - AMBIENT) * cos)) == 203
    assert (image[covered] == 203).all() and (image[~covered] == BACKGROUND).all()


def test_the_nearer_face_hides_the_farther_one_whatever_the_order():
    near, f = square(2.0, 0.25)
    far, _ = square(3.0, 1.0)
    colours = np.r_[np.tile([1.0, 0, 0], (4, 1)), np.tile([0, 0, 1.0], (4, 1))]
    for order in ([0, 1], [1, 0]):
        parts = [(near, f), (far, f + 4)]
        v = np.r_[near, far]
        faces = np.r_[parts[order[0]][1], parts[order[1]][1]]
        image, depth = shade_mesh(v, faces, K, EYE, 100, 100, colours)
        assert np.isclose(depth[50, 50], 2.0) and image[50, 50, 0] > 240 and image[50, 50, 2] == 0
        assert np.isclose(depth[50, 20], 3.0) and image[50, 20, 2] > 240 and image[50, 20, 0] == 0


def test_a_tilted_face_is_dimmer_by_the_cosine():
    """A small square turned 60 degrees about the y axis, straight ahead: |n . d| = 1/2."""
    v, f = square(0.0, 0.05)
    c, s = math.cos(math.radians(60)), math.sin(math.radians(60))
    v = v @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]).T + [0, 0, 2.0]
    image, _ = shade_mesh(v, f, K, EYE, 100, 100)
    expected = round(0.8 * 255 * (AMBIENT + (1 - AMBIENT) * 0.5))
    assert abs(int(image[50, 50, 0]) - expected) <= 1


def brute_force_depth(vertices, faces, K, width, height):
    """Depth of the nearest face hit by the ray through each pixel centre (Moller-Trumbore)."""
    depth = np.full((height, width), np.inf)
    Kinv = np.linalg.inv(K)
    for v in range(height):
        for u in range(width):
            d = Kinv @ [u + 0.5, v + 0.5, 1.0]
            for a, b, c in vertices[faces]:
                e1, e2 = b - a, c - a
                p = np.cross(d, e2)
                det = e1 @ p
                if abs(det) < 1e-12:
                    continue
                s = -a
                w1 = (s @ p) / det
                q = np.cross(s, e1)
                w2 = (d @ q) / det
                t = (e2 @ q) / det
                if w1 >= 0 and w2 >= 0 and w1 + w2 <= 1 and t > 0:
                    depth[v, u] = min(depth[v, u], t)  # d has z = 1: t is the depth
    return depth


def test_matches_a_brute_force_ray_caster():
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=0.6)
    vertices = np.asarray(sphere.vertices) + [0.05, -0.03, 2.5]
    K32 = np.array([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    _, depth = shade_mesh(vertices, np.asarray(sphere.faces), K32, EYE, 32, 32)
    twin = brute_force_depth(vertices, np.asarray(sphere.faces), K32, 32, 32)
    both = np.isfinite(depth) & np.isfinite(twin)
    assert (np.isfinite(depth) != np.isfinite(twin)).sum() <= 2  # edge ties at most
    assert both.sum() > 250 and np.abs(depth[both] - twin[both]).max() < 1e-9


def test_preview_views_are_spread_over_the_training_views():
    assert preview_views(100, 3) == [0, 33, 67]
    assert preview_views(2, 3) == [0, 1]


def test_vertex_normals_shade_a_sphere_like_its_faces_but_smoothly():
    """Given the exact normals of a finely tessellated sphere, the smooth shade differs from
    the flat one by little on average, and at the centre (n . d = 1) is 0.8 x 255 = 204."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.6)
    vertices = np.asarray(sphere.vertices) + [0.0, 0.0, 2.5]
    normals = np.asarray(sphere.vertices) / 0.6
    flat, depth = shade_mesh(vertices, np.asarray(sphere.faces), K, EYE, 100, 100)
    smooth, depth2 = shade_mesh(vertices, np.asarray(sphere.faces), K, EYE, 100, 100, None, normals)
    assert np.array_equal(depth, depth2)
    covered = np.isfinite(depth)
    assert np.abs(smooth[covered].astype(int) - flat[covered].astype(int)).mean() < 3
    assert abs(int(smooth[50, 50, 0]) - 204) <= 1
    # turning the camera turns the normals with it: same picture from a rotated frame
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    world = vertices @ R  # world points whose cam_from_world is R
    cfw = np.eye(4)
    cfw[:3, :3] = R
    turned, _ = shade_mesh(world, np.asarray(sphere.faces), K, cfw, 100, 100, None, normals @ R)
    assert np.abs(turned.astype(int) - smooth.astype(int)).max() <= 1
