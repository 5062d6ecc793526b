"""`recon sfm --from-llff`: LLFF's poses_bounds.npy -> OpenCV cameras (recon.sfm.sources)."""

import json

import cv2
import numpy as np
import pytest

from recon.sfm.sources import SourceError, opencv_c2w_from_llff, read_llff
from tests.conftest import SHARED_DATA, recon_cli

FLOWER = SHARED_DATA / "llff_flower"


def test_llff_axes_to_opencv_worked_example():
    # LLFF's camera axes (down, right, back) as the world's (x, y, z): an OpenCV camera then has
    # right = world y, down = world x, forward = -z
    pose = np.concatenate([np.eye(3), [[1.0], [2.0], [3.0]]], 1)
    c2w = opencv_c2w_from_llff(pose)
    assert np.allclose(c2w[:3, :3], [[0, 1, 0], [1, 0, 0], [0, 0, -1]])
    assert np.allclose(c2w[:3, 3], [1, 2, 3])
    assert np.linalg.det(c2w[:3, :3]) == pytest.approx(1.0)  # still a rotation


def _fake_llff(root, n=9, size=(40, 30)):
    (root / "images_4").mkdir(parents=True)
    rows = []
    for i in range(n):
        cv2.imwrite(
            str(root / "images_4" / f"im{i:03d}.png"), np.full((size[1], size[0], 3), i, np.uint8)
        )
        mat = np.concatenate(
            [np.eye(3), [[0.0], [i * 0.1], [0.0]], [[4 * size[1]], [4 * size[0]], [200.0]]], 1
        )
        rows.append(np.concatenate([mat.ravel(), [1.5, 20.0]]))
    np.save(root / "poses_bounds.npy", np.array(rows))


def test_read_llff_scales_the_focal_and_holds_out_every_8th(tmp_path):
    _fake_llff(tmp_path)
    posed = read_llff(tmp_path)
    assert [f.name for f in posed.frames if f.split == "test"] == ["im000", "im008"]
    K = posed.frames[0].K
    assert K[0, 0] == pytest.approx(50.0)  # focal 200 at 4x the files' width
    assert (K[0, 2], K[1, 2]) == (20.0, 15.0)
    assert posed.extra["llff_bounds"] == {"near": 1.5, "far": 20.0}
    assert posed.points is None


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda r: (r / "poses_bounds.npy").unlink(), "poses_bounds.npy"),
        (lambda r: (r / "images_4" / "im003.png").unlink(), "9 poses but"),
        (lambda r: np.save(r / "poses_bounds.npy", np.zeros((9, 15))), r"\(N, 17\)"),
        (lambda r: (r / "poses_bounds.npy").write_bytes(b"junk"), "cannot read"),
    ],
)
def test_read_llff_bad_input_says_why(tmp_path, change, match):
    _fake_llff(tmp_path)
    change(tmp_path)
    with pytest.raises(SourceError, match=match):
        read_llff(tmp_path)


@pytest.mark.skipif(not FLOWER.exists(), reason="../shared/data/llff_flower is missing")
def test_flower_poses_satisfy_the_epipolar_constraint_of_their_photos():
    """The imported cameras of two flower photos predict where SIFT matches between the photos
    lie (x2^T F x1 = 0, F from the relative pose and K): a wrong axis order, focal scale or
    principal point gives errors of many pixels."""
    posed = read_llff(FLOWER)
    a, b = posed.frames[0], posed.frames[3]
    grey = [cv2.imread(str(f.path), cv2.IMREAD_GRAYSCALE) for f in (a, b)]
    sift = cv2.SIFT_create(2000)
    (ka, da), (kb, db) = (sift.detectAndCompute(g, None) for g in grey)
    pairs = [m for m, n in cv2.BFMatcher().knnMatch(da, db, k=2) if m.distance < 0.7 * n.distance]
    x1 = np.array([ka[m.queryIdx].pt for m in pairs]) + 0.5  # OpenCV keypoints: pixel centres at 0
    x2 = np.array([kb[m.trainIdx].pt for m in pairs]) + 0.5
    b_from_a = np.linalg.inv(b.world_from_cam) @ a.world_from_cam
    R, t = b_from_a[:3, :3], b_from_a[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(b.K).T @ tx @ R @ np.linalg.inv(a.K)
    h1, h2 = np.c_[x1, np.ones(len(x1))], np.c_[x2, np.ones(len(x2))]
    lines = h1 @ F.T  # epipolar lines in photo b
    dist = np.abs((h2 * lines).sum(1)) / np.linalg.norm(lines[:, :2], axis=1)
    assert len(pairs) > 200
    assert np.median(dist) < 1.0  # pixels, at 1008 x 756


@pytest.mark.skipif(not FLOWER.exists(), reason="../shared/data/llff_flower is missing")
def test_cli_from_llff_writes_the_workspace(tmp_path):
    ws = tmp_path / "ws"
    out = recon_cli("sfm", "--from-llff", str(FLOWER), "-w", str(ws), "--downscale", "4", "--json")
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    assert report["images"] == 34 and report["splits"] == {"test": 5, "train": 29}
    cams = json.loads((ws / "sfm" / "cameras.json").read_text())
    assert cams["unbounded"] is True
    bad = recon_cli(
        "sfm", "--from-llff", str(tmp_path / "nothing"), "-w", str(tmp_path / "ws2"), check=False
    )
    assert bad.returncode == 1 and "poses_bounds.npy" in bad.stderr
    assert not (tmp_path / "ws2").exists()
