import json

import numpy as np
import pytest

from recon.cameras.similarity import Similarity
from recon.sfm.normalize import normalize_scene, rotation_between
from recon.sfm.sources import SourceError, holdout_split, read_colmap, read_transforms
from tests.conftest import recon_cli


def test_read_blender_folder_keeps_split(blender_dataset):
    posed = read_transforms(blender_dataset)
    splits = [f.split for f in posed.frames]
    assert splits.count("train") == 4 and splits.count("test") == 2
    f = posed.frames[0]
    assert f.K[0, 0] == pytest.approx(0.5 * 16 / np.tan(0.5 * 0.69))
    # OpenCV: the camera looks at the origin along +z of its frame
    fwd = f.world_from_cam[:3, 2]
    assert np.allclose(fwd, -f.world_from_cam[:3, 3] / np.linalg.norm(f.world_from_cam[:3, 3]))


def test_single_transforms_file_uses_every_8th_holdout(tmp_path, blender_dataset):
    meta = json.loads((blender_dataset / "transforms_train.json").read_text())
    meta["frames"] = meta["frames"] * 4
    for i, fr in enumerate(meta["frames"]):
        fr["file_path"] = f"./train/r_{i % 4}"
    (blender_dataset / "transforms.json").write_text(json.dumps(meta))
    posed = read_transforms(blender_dataset / "transforms.json")
    assert [f.split for f in posed.frames].count("test") == 2  # 16 frames -> 2 held out


def test_holdout_split_every_8th_in_name_order():
    names = [f"img{i:02d}" for i in range(17)][::-1]
    split = holdout_split(names)
    held = sorted(n for n, s in zip(names, split) if s == "test")
    assert held == ["img00", "img08", "img16"]


@pytest.mark.parametrize(
    "content,match",
    [
        ("{oops", "not valid JSON"),
        ('{"frames": []}', "no frames"),
        ('{"a": 1}', "no 'frames'"),
        ('{"camera_angle_x": 1, "frames": [{"file_path": "x"}]}', "lacks"),
    ],
)
def test_malformed_transforms(tmp_path, content, match):
    p = tmp_path / "transforms.json"
    p.write_text(content)
    with pytest.raises(SourceError, match=match):
        read_transforms(p)


def test_normalization_puts_cameras_in_unit_box_and_up_is_z():
    rng = np.random.default_rng(0)
    c2w = []
    for a in np.linspace(0, 2 * np.pi, 12, endpoint=False):
        eye = np.array([np.cos(a), np.sin(a), 0.3]) * 50 + np.array([100, -20, 7])
        fwd = (np.array([100, -20, 7]) - eye) / np.linalg.norm(np.array([100, -20, 7]) - eye)
        right = np.cross(fwd, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(fwd, right), fwd, eye
        c2w.append(m)
    c2w = np.stack(c2w)
    K = np.tile(np.array([[100, 0, 50], [0, 100, 50], [0, 0, 1.0]]), (12, 1, 1))
    pts = rng.normal(size=(500, 3)) * 5 + np.array([100, -20, 7])
    sim, aabb = normalize_scene(c2w, K, np.full((12, 2), 100.0), pts)
    cams = sim.apply(c2w[:, :3, 3])
    assert np.abs(cams).max() <= 0.9 + 1e-9
    assert np.all(aabb[0] < 0) and np.all(aabb[1] > 0) and np.abs(aabb).max() <= 1
    assert np.allclose(sim.invert_points(sim.apply(pts)), pts)
    s2c = sim.world_from_cam_to_scene(c2w)
    assert np.allclose(
        -s2c[:, :3, 1].mean(0) / np.linalg.norm(s2c[:, :3, 1].mean(0)), [0, 0, 1], atol=1e-9
    )
    assert isinstance(Similarity.from_json(sim.to_json()), Similarity)


def test_rotation_between_opposite_vectors():
    R = rotation_between(np.array([0, 0, -1.0]), np.array([0, 0, 1.0]))
    assert np.allclose(R @ [0, 0, -1.0], [0, 0, 1]) and np.isclose(np.linalg.det(R), 1)


def test_import_then_reimport_colmap_model_round_trip(tmp_path, blender_dataset):
    import zlib  # noqa: F401

    import pycolmap

    ws = tmp_path / "ws"
    recon_cli("sfm", "--from-transforms", str(blender_dataset), "-w", str(ws))
    rec = pycolmap.Reconstruction(str(ws / "sfm" / "sparse"))
    assert rec.num_images() == 6 and all(c.model_name == "PINHOLE" for c in rec.cameras.values())
    cams = json.loads((ws / "sfm" / "cameras.json").read_text())
    posed = read_colmap(ws / "sfm" / "sparse", ws / "images")
    original = read_transforms(blender_dataset)
    by_path = {f"{f.split}/{f.name}": f for f in original.frames}
    for f in posed.frames:
        ref = by_path[f.path.relative_to(ws / "images").with_suffix("").as_posix()]
        assert np.allclose(f.world_from_cam, ref.world_from_cam, atol=1e-6)
        assert np.allclose(f.K, ref.K, atol=1e-6)
    assert len(cams["frames"]) == 6
