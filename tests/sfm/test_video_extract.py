"""Decoding and writing video frames (recon/sfm/video_extract.py) on small videos made here
with cv2.VideoWriter (mp4v) and remuxed with imageio-ffmpeg's ffmpeg: the one-pass extraction
against its two-pass twin, truncated files, display rotation, several videos, bad videos."""

import subprocess
from pathlib import Path

import cv2
import imageio_ffmpeg
import numpy as np
import pytest

from recon.sfm.video import VideoConfig, frame_name, sharpest_in_windows, window_bounds
from recon.sfm.video_extract import (
    VideoError,
    extract_video,
    extract_videos,
    quiet_decoder,
    scan_video,
    unique_stems,
    video_report,
    write_frames,
)
from tests.sfm.test_video import EXPECTED_CHOSEN, EXPECTED_DROPPED, pan_sequence


def no_progress(*_args) -> None:
    pass


def write_video(path: Path, frames: list[np.ndarray], fps: float = 10.0) -> Path:
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    for f in frames:
        writer.write(f)
    writer.release()
    return path


def scramble_frames(video: Path, out: Path) -> Path:
    """A copy of an mp4v file whose index is intact and whose frame data is noise: it opens,
    announces its frames, and none of them decodes."""
    data = bytearray(video.read_bytes())
    start, end = data.find(b"mdat") + 4, data.find(b"moov") - 4
    data[start:end] = np.random.default_rng(1).bytes(end - start)
    out.write_bytes(bytes(data))
    return out


def ffmpeg(*args: str) -> None:
    subprocess.run(
        [imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-loglevel", "error", "-y", *args],
        check=True,
        capture_output=True,
    )


@pytest.fixture(scope="module")
def pan_video(tmp_path_factory) -> Path:
    return write_video(tmp_path_factory.mktemp("video") / "pan walk.mp4", pan_sequence())


def two_pass_twin(path: Path, out: Path, stem: str, windows: int, ratio: float) -> list[str]:
    """The obviously correct extraction: score every frame, choose on the true frame count,
    decode again and write the chosen frames, delete the blurred ones."""
    out.mkdir()
    scores, written = scan_video(path, None, out, stem, no_progress)
    assert written == []
    chosen = sharpest_in_windows(scores, window_bounds(len(scores), windows))
    write_frames(path, chosen, out, stem, no_progress)
    for i in chosen[scores[chosen] < ratio * np.median(scores[chosen])]:
        (out / frame_name(stem, int(i))).unlink()
    return sorted(p.name for p in out.iterdir())


def files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_video_keeps_the_sharpest_of_each_window_and_drops_blurred(pan_video, tmp_path):
    out = tmp_path / "frames"
    (video,) = extract_videos([pan_video], out, VideoConfig(frames=8), no_progress)
    kept = [i for i in EXPECTED_CHOSEN if i not in EXPECTED_DROPPED]
    assert video.chosen.tolist() == EXPECTED_CHOSEN and video.kept.tolist() == kept
    assert video.passes == 1 and video.stem == "pan_walk"
    assert (
        sorted(p.name for p in out.iterdir())
        == video.names
        == [f"pan_walk_{i:06d}.png" for i in kept]
    )
    assert cv2.imread(str(out / video.names[0])).shape == (200, 320, 3)
    report = video_report(video)
    assert report["frames_decoded"] == report["frames_announced"] == 24
    assert report["windows"] == 8 and report["frames_kept"] == 6 and report["fps"] == 10.0
    assert [k["frame"] for k in report["kept"]] == kept
    assert report["kept"][0]["time_s"] == pytest.approx(kept[0] / 10)
    blurred = [d for d in report["dropped"] if d["reason"].startswith("blurred")]
    assert [d["frame"] for d in blurred] == EXPECTED_DROPPED
    median = report["sharpness"]["median_of_chosen"]
    assert blurred[0]["reason"] == (
        f"blurred: Laplacian variance {blurred[0]['sharpness']:.1f} < 0.35 x median {median:.1f}"
    )
    others = [d for d in report["dropped"] if not d["reason"].startswith("blurred")]
    assert len(others) == 8 and sum(d["count"] for d in others) == 16
    assert others[0] == {
        "frames": [0, 2],
        "count": 2,
        "reason": "not the sharpest of its window (frame 1 is)",
    }


@pytest.mark.parametrize(
    "config",
    [
        VideoConfig(frames=8),
        VideoConfig(frames=0, fps=2.0),
        VideoConfig(frames=100, blur_ratio=0.0),
    ],
)
def test_one_pass_extraction_matches_two_pass_twin(pan_video, tmp_path, config):
    out = tmp_path / "one"
    out.mkdir()
    video = extract_video(pan_video, out, "v", config.frames, config, no_progress)
    windows = {8: 8, 0: 5, 100: 24}[config.frames]  # fps 2 over 2.4 s of video: round(4.8)
    assert video.passes == 1 and len(video.chosen) == windows
    twin = two_pass_twin(pan_video, tmp_path / "twin", "v", windows, config.blur_ratio)
    assert twin == video.names
    assert files(out) == files(tmp_path / "twin")  # same frames, bit for bit


def test_truncated_video_is_chosen_on_its_decoded_frames(pan_video, tmp_path):
    """A file cut short (moov atom first, so it still opens) announces 24 frames but decodes
    fewer: the windows move to the true count and a second pass writes those frames."""
    whole = tmp_path / "faststart.mp4"
    ffmpeg("-i", str(pan_video), "-c", "copy", "-movflags", "+faststart", str(whole))
    cut = tmp_path / "cut.mp4"
    data = whole.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    out = tmp_path / "one"
    out.mkdir()
    video = extract_video(cut, out, "cut", 5, VideoConfig(frames=5), no_progress)
    decoded = len(video.scores)
    assert 0 < decoded < 24 and video.info.frames_announced == 24 and video.passes == 2
    assert video.bounds.tolist() == window_bounds(decoded, 5).tolist()
    assert files(out) == {
        n: (tmp_path / "twin" / n).read_bytes()
        for n in two_pass_twin(cut, tmp_path / "twin", "cut", 5, 0.35)
    }
    assert "announces 24" in video_report(video)["notes"][0]


def test_display_rotation_is_applied(pan_video, tmp_path):
    """Phones store portrait video sideways with a display rotation; frames come out upright
    (as players show them), and the report says which rotation was applied."""
    rotated = tmp_path / "portrait.mp4"
    ffmpeg("-display_rotation", "90", "-i", str(pan_video), "-c", "copy", str(rotated))
    out = tmp_path / "frames"
    (video,) = extract_videos([rotated], out, VideoConfig(frames=8, blur_ratio=0.0), no_progress)
    assert (video.info.width, video.info.height, video.info.rotation_deg) == (200, 320, 270)
    (plain,) = extract_videos(
        [pan_video], tmp_path / "plain", VideoConfig(frames=8, blur_ratio=0.0), no_progress
    )
    assert video.chosen.tolist() == plain.chosen.tolist()  # rotation does not change sharpness
    upright = cv2.imread(str(out / video.names[0]))
    original = cv2.imread(str(tmp_path / "plain" / plain.names[0]))
    assert upright.shape == (320, 200, 3)
    assert np.array_equal(upright, np.rot90(original, 1))  # 90 degrees counter-clockwise
    assert video_report(video)["rotation_deg"] == 270


def test_several_videos_share_the_frame_budget_by_duration(tmp_path):
    frames = pan_sequence(96, 128)
    a = write_video(tmp_path / "a.mp4", frames)  # 2.4 s
    b = write_video(tmp_path / "a.mov", frames[:12], fps=5.0)  # 2.4 s
    c = write_video(tmp_path / "c.mp4", frames[:12])  # 1.2 s
    assert unique_stems([a, b, c]) == ["a_mp4", "a_mov", "c"]
    videos = extract_videos(
        [a, b, c], tmp_path / "out", VideoConfig(frames=10, blur_ratio=0.0), no_progress
    )
    assert [len(v.chosen) for v in videos] == [4, 4, 2]
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == sorted(n for v in videos for n in v.names)
    assert names[0].startswith("a_mov_") and names[-1].startswith("c_")


def test_bad_videos_raise_one_line_errors(pan_video, tmp_path):
    garbage = tmp_path / "garbage.mp4"
    garbage.write_bytes(np.random.default_rng(0).bytes(5000))
    header_only = tmp_path / "empty.mp4"  # a writer closed before any frame
    cv2.VideoWriter(str(header_only), cv2.VideoWriter_fourcc(*"mp4v"), 10, (64, 64)).release()
    scrambled = scramble_frames(pan_video, tmp_path / "scrambled.mp4")
    cases = [
        (garbage, "cannot read video"),
        (header_only, "cannot read video"),
        (scrambled, "no decodable frames"),
        (tmp_path / "missing.mp4", "does not exist"),
    ]
    for path, message in cases:
        out = tmp_path / f"out-{path.stem}"
        with quiet_decoder(False), pytest.raises(VideoError, match=message) as info:
            extract_videos([path], out, VideoConfig(), no_progress)
        assert isinstance(info.value, ValueError) and "\n" not in str(info.value)
