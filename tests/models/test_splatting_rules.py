"""The rules 3dgs applies to its config and scene, each on its own: the scene extent of a
forward-facing capture and what "auto" antialiasing resolves to."""

import pytest
import torch

from recon.cameras import Cameras
from tests.models.test_splatting import config


def _row_of_cameras(xs, focal=50.0, size=32):
    """Cameras at (x, 0, 0) looking down +z (OpenCV), world = camera frame shifted by x."""
    n = len(xs)
    cfw = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    cfw[:, 0, 3] = -torch.tensor(xs, dtype=torch.float64)
    K = torch.tensor([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]], dtype=torch.float64)
    wh = torch.full((n,), size)
    return Cameras(K.expand(n, 3, 3).clone(), cfw, wh, wh.clone())


def test_scene_extent_of_a_forward_facing_capture_is_its_depth():
    from recon.models.splatting_rules import median_point_depth, scene_extent

    cams = _row_of_cameras([-0.5, 0.0, 0.5])  # camera extent 1.1 x 0.5 = 0.55
    points = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 4.0], [0.0, 0.0, 9.0], [0, 0, -1.0]])
    assert median_point_depth(cams, points) == 4.0  # the point behind the cameras is left out
    assert scene_extent(cams, points, "cameras") == pytest.approx(0.55)
    assert scene_extent(cams, points, "depth") == pytest.approx(4.4)
    assert scene_extent(cams, points, "auto") == pytest.approx(4.4)  # 0.55 < 0.5 x 4.4
    near = points * torch.tensor([1.0, 1.0, 0.2])  # depths 0.4, 0.8, 1.8: 0.55 >= 0.5 x 0.88
    assert scene_extent(cams, near, "auto") == pytest.approx(0.55)
    assert scene_extent(cams, None, "auto") == pytest.approx(0.55)
    with pytest.raises(ValueError, match="extent must be one of"):
        scene_extent(cams, points, "median")


def test_antialiasing_is_on_for_real_captures_by_default():
    from recon.models.splatting_rules import uses_antialiasing

    assert uses_antialiasing(config(), True) and not uses_antialiasing(config(), False)
    for given, expected in ((True, True), (False, False), ("true", True), ("off", False)):
        assert uses_antialiasing(config(antialiased=given), True) is expected  # saved booleans too
        assert uses_antialiasing(config(antialiased=given), False) is expected
    with pytest.raises(ValueError, match="antialiased must be on, off or auto"):
        uses_antialiasing(config(antialiased="sometimes"), True)
