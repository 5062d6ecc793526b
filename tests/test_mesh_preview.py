"""The mesh preview: a shaded picture of a mesh from one camera."""

import numpy as np
import trimesh

from recon.mesh.preview import AMBIENT, BASE_GREY, shaded_view


def test_sphere_seen_head_on_is_brightest_at_its_centre_and_white_around():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    sphere.apply_translation([0, 0, 4])
    K = np.array([[40.0, 0, 32], [0, 40.0, 32], [0, 0, 1]])
    image = shaded_view(sphere, K, np.eye(4), 64, 64)
    assert image.shape == (64, 64, 3) and image.dtype == np.uint8
    assert (image[0, 0] == 255).all() and (image[-1, -1] == 255).all()  # background
    centre = image[32, 32, 0] / 255
    assert abs(centre - BASE_GREY) < 0.02  # n . v = 1 at the centre
    rim = image[32, 32 + 9, 0] / 255  # the sphere's silhouette is ~10 px from the centre
    assert AMBIENT * BASE_GREY - 0.02 < rim < centre
    # field normals given per vertex shade the same sphere the same way
    with_normals = shaded_view(sphere, K, np.eye(4), 64, 64, sphere.vertex_normals)
    assert np.abs(with_normals.astype(int) - image.astype(int)).mean() < 3
