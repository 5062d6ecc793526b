"""Pictures of an evaluated view: the error heat map's fixed scale and the depth colouring."""

import cv2
import numpy as np

from recon.eval.visuals import ERROR_MAX, depth_map, error_map, write_view_pictures


def turbo(t):
    return cv2.applyColorMap(np.array([[round(255 * t)]], np.uint8), cv2.COLORMAP_TURBO)[0, 0, ::-1]


def test_error_map_uses_one_fixed_scale():
    gt = np.zeros((2, 3, 3))
    pred = gt.copy()
    pred[0, 1] = ERROR_MAX  # exactly the top of the scale
    pred[0, 2] = 1.0  # beyond it: clipped
    pred[1, 0] = ERROR_MAX / 2
    heat = error_map(pred, gt)
    assert (heat[0, 0] == turbo(0)).all() and (heat[0, 1] == turbo(1)).all()
    assert (heat[0, 2] == turbo(1)).all() and (heat[1, 0] == turbo(0.5)).all()


def test_depth_map_is_black_where_the_render_is_empty_and_near_is_warm():
    depth = np.array([[1.0, 2.0, 4.0, 0.0]])
    acc = np.array([[1.0, 1.0, 1.0, 0.0]])
    pic = depth_map(depth, acc)
    assert (pic[0, 3] == 0).all()
    assert pic[0, 0, 0] > pic[0, 0, 2] and pic[0, 2, 2] > pic[0, 2, 0]  # near red, far blue
    assert (depth_map(depth, np.zeros_like(acc)) == 0).all()


def test_four_pictures_and_thumbnails_per_view(tmp_path):
    rng = np.random.default_rng(0)
    gt, pred = rng.random((2, 300, 450, 3))
    out = write_view_pictures(
        tmp_path, "r_7.png", gt, pred, np.ones((300, 450)), np.ones((300, 450))
    )
    assert set(out) == {"gt", "render", "error", "depth"}
    for kind, names in out.items():
        full = cv2.imread(str(tmp_path / names["full"]))
        thumb = cv2.imread(str(tmp_path / names["thumb"]))
        assert full.shape == (300, 450, 3) and thumb.shape == (133, 200, 3), kind
