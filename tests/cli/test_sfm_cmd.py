"""`recon sfm VIDEO` and `recon sfm FOLDER` (photos + videos) end to end through the CLI, on
videos made here from the sample scene's orbit; bad videos give one line and leave the
workspace as it was; a changed video makes the sfm stage stale."""

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from recon.cli.sfm_cmd import _video_config
from tests.conftest import SAMPLE_DATA, recon_cli
from tests.sfm.test_video_extract import scramble_frames

BLURRED_VIEWS = (7, 13)  # views filmed "during a fast pan": all their frames are blurred


def orbit_video(path: Path, views: list[int], blurred_views=BLURRED_VIEWS) -> Path:
    """A 10 fps MP4 of sample_data views in orbit order (r_000..r_019 is the 30-degree ring,
    see its transforms.json), 3 frames per view: blurred (sigma 2 px), sharp, blurred
    (1.5 px); the 3 frames of `blurred_views` are all blurred (2, 3, 1.5 px)."""
    first = cv2.imread(str(SAMPLE_DATA / "images" / "r_000.png"))
    h, w = first.shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (w, h))
    for v in views:
        image = cv2.imread(str(SAMPLE_DATA / "images" / f"r_{v:03d}.png"))
        for sigma in (2.0, 0.0, 1.5):
            if sigma == 0.0:
                sigma = 3.0 if v in blurred_views else 0.0
            writer.write(cv2.GaussianBlur(image, (0, 0), sigma) if sigma else image)
    writer.release()
    return path


def snapshot(ws: Path) -> dict:
    return {
        p.relative_to(ws): p.read_bytes()
        for p in ws.rglob("*")
        if p.is_file() and ".locks" not in p.parts
    }


def assert_one_line_error(proc, match: str) -> None:
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and match in lines[0], proc.stderr


@pytest.mark.slow
def test_video_to_poses_keeps_sharp_frames_and_tracks_the_video(tmp_path):
    video = orbit_video(tmp_path / "orbit.mp4", list(range(20)))
    ws = tmp_path / "ws"
    out = recon_cli("sfm", str(video), "-w", str(ws), "--frames", "20").stdout
    assert (
        "1 video: 60 frames decoded, 20 extracted (sharpest per window), 18 kept (2 too blurred)"
    ) in out
    report = json.loads((ws / "sfm" / "report.json").read_text())
    kept = [f"orbit_{3 * v + 1:06d}.png" for v in range(20) if v not in BLURRED_VIEWS]
    (clip,) = report["video"]["videos"]
    assert [k["name"] for k in clip["kept"]] == kept
    assert sorted(p.name for p in (ws / "sfm" / "frames").iterdir()) == kept
    blurred = [d for d in clip["dropped"] if d["reason"].startswith("blurred")]
    assert [d["frame"] for d in blurred] == [3 * v + 2 for v in BLURRED_VIEWS]  # sigma 1.5
    assert clip["dropped"][0]["reason"] == "not the sharpest of its window (frame 1 is)"
    assert report["config"]["matcher"] == "sequential"
    assert report["images_usable"] == report["images_registered"] == 18
    assert report["unregistered"] == []
    # the video is the stage's input: changing it makes sfm stale
    record = json.loads((ws / "workspace.json").read_text())["stages"]["sfm"]
    assert list(record["inputs"]) == [str(video.resolve())]
    status = json.loads(recon_cli("status", "-w", str(ws), "--json").stdout)["stages"]
    assert [(s["stage"], s["state"]) for s in status] == [("sfm", "done")]
    orbit_video(video, list(range(19)))
    status = json.loads(recon_cli("status", "-w", str(ws), "--json").stdout)["stages"]
    assert status[0]["state"] == "stale" and "changed" in status[0]["why"]


@pytest.mark.slow
def test_folder_of_photos_and_a_video_uses_both(tmp_path):
    folder = tmp_path / "capture"
    folder.mkdir()
    for v in range(1, 20, 2):  # odd views as photos, even views filmed
        shutil.copy(SAMPLE_DATA / "images" / f"r_{v:03d}.png", folder)
    orbit_video(folder / "walk around.MOV", list(range(0, 20, 2)), blurred_views=())
    report = json.loads(
        recon_cli("sfm", str(folder), "-w", str(tmp_path / "ws"), "--frames", "10", "--json").stdout
    )
    frames = [k["name"] for k in report["video"]["videos"][0]["kept"]]
    assert frames == [f"walk_around_{3 * i + 1:06d}.png" for i in range(10)]
    assert report["skipped"] == [] and report["images_usable"] == 20
    assert report["images_registered"] == 20 and report["config"]["matcher"] == "sequential"
    names = {
        f["name"]
        for f in json.loads((tmp_path / "ws" / "sfm" / "cameras.json").read_text())["frames"]
    }
    assert {"r_001", "walk_around_000001"} <= names


def test_bad_videos_give_one_line_and_leave_the_workspace_as_it_was(tmp_path, blender_dataset):
    garbage = tmp_path / "garbage.mp4"
    garbage.write_bytes(np.random.default_rng(0).bytes(5000))
    good = orbit_video(tmp_path / "good.mp4", [0, 1])
    scrambled = scramble_frames(good, tmp_path / "scrambled.mp4")  # opens, 0 frames decode
    wmv = tmp_path / "clip.wmv"
    wmv.write_bytes(b"\0" * 100)
    folder = tmp_path / "mixed"
    folder.mkdir()
    shutil.copy(SAMPLE_DATA / "images" / "r_000.png", folder)
    shutil.copy(garbage, folder / "b.mp4")
    ws = tmp_path / "ws"
    for source, message in [
        (garbage, "cannot read video"),
        (scrambled, "no decodable frames"),
        (wmv, "neither a folder nor a video"),
    ]:
        assert_one_line_error(recon_cli("sfm", str(source), "-w", str(ws), check=False), message)
        assert not ws.exists()  # a failed first run leaves no directory behind
    assert_one_line_error(
        recon_cli("sfm", str(SAMPLE_DATA / "images"), "-w", str(ws), "--frames", "5", check=False),
        "apply to videos",
    )
    assert not ws.exists()
    recon_cli("sfm", "--from-transforms", str(blender_dataset), "-w", str(ws))
    before = snapshot(ws)
    for source, message in [(folder, "cannot read video"), (scrambled, "no decodable frames")]:
        assert_one_line_error(recon_cli("sfm", str(source), "-w", str(ws), check=False), message)
        assert snapshot(ws) == before  # a failed rerun leaves images/ and sfm/ as they were
    assert sorted(p.name for p in ws.iterdir()) == [".locks", "images", "sfm", "workspace.json"]


def test_video_flags(tmp_path):
    """The flags -> VideoConfig, in process (the subprocess tests above show the one line)."""
    video = orbit_video(tmp_path / "v.mp4", [0])
    assert _video_config(video, None, None, None) is None  # defaults apply later
    assert _video_config(video, 40, None, None).frames == 40
    config = _video_config(video, None, 2.0, 0.0)
    assert (config.frames, config.fps, config.blur_ratio) == (0, 2.0, 0.0)
    with pytest.raises(ValueError, match="not both"):
        _video_config(video, 40, 2.0, None)
    with pytest.raises(ValueError, match="exactly one"):
        _video_config(video, 0, None, None)
    with pytest.raises(ValueError, match="apply to videos"):
        _video_config(SAMPLE_DATA / "images", None, None, 0.2)


@pytest.mark.slow
def test_retrieval_matcher_from_the_command_line(tmp_path):
    """`--matcher retrieval --retrieval-neighbors 8` on the 40 sample photos: each photo meets
    its 8 most similar ones (between 160 and 320 of the 780 pairs) and every photo registers."""
    ws = tmp_path / "ws"
    recon_cli(
        "sfm",
        str(SAMPLE_DATA / "images"),
        "-w",
        str(ws),
        "--matcher",
        "retrieval",
        "--retrieval-neighbors",
        "8",
    )
    report = json.loads((ws / "sfm" / "report.json").read_text())
    assert report["config"]["matcher"] == "retrieval"
    assert report["config"]["retrieval_neighbors"] == 8
    assert 40 * 8 // 2 <= report["attempts"][0]["pairs_matched"] <= 40 * 8
    assert report["images_registered"] == 40
