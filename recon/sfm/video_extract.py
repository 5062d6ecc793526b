"""Decoding videos (OpenCV's bundled FFmpeg) and writing the frames `video` chooses as PNGs.

One decoding pass normally suffices: the windows are laid out on the frame count the
container announces, each window's sharpest frame is written as soon as the window ends, and
the blurred ones are deleted once the whole video's median sharpness is known. When the
decoded count differs from the announced one (a truncated file, a container that only
estimates its count) the windows move, so the choice is recomputed on the true count and a
second pass writes exactly those frames (`write_frames`, which is also the slow twin the
single pass is tested against).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from recon.sfm.video import (
    VideoConfig,
    blur_threshold,
    frame_budgets,
    frame_name,
    frame_sharpness,
    frame_stem,
    measure_size,
    sharpest_in_windows,
    window_bounds,
    windows_for,
)

Progress = Callable[[str, int, int | None], None]


class VideoError(ValueError):
    """A video that cannot be used (unreadable, corrupt, no frames); the message is one line."""


@dataclass(frozen=True)
class VideoInfo:
    """What the container says about a video (frames upright, as they will be written)."""

    path: Path
    frames_announced: int  # frame count in the container (0 if unknown; may be an estimate)
    fps: float  # frames per second (0 if unknown)
    width: int  # upright size in pixels (after the display rotation)
    height: int
    rotation_deg: int  # clockwise display rotation from the metadata, applied to every frame
    codec: str  # FourCC, e.g. avc1, hvc1, mp4v


@dataclass(frozen=True)
class VideoFrames:
    """The frames chosen from one video and why the others were not."""

    info: VideoInfo
    stem: str  # frame files are <stem>_<index>.png
    scores: np.ndarray  # (N,) sharpness of every decoded frame
    bounds: np.ndarray  # (K + 1,) window boundaries over the N frames
    chosen: np.ndarray  # (K,) the sharpest frame of each window
    threshold: float  # blur_ratio x median score of the chosen frames
    blur_ratio: float
    passes: int  # decoding passes (2 when the announced frame count was wrong)

    @property
    def kept(self) -> np.ndarray:
        """Chosen frames that are not blurred, in video order."""
        return self.chosen[self.scores[self.chosen] >= self.threshold]

    @property
    def names(self) -> list[str]:
        return [frame_name(self.stem, int(i)) for i in self.kept]


@contextlib.contextmanager
def quiet_decoder(verbose: bool):
    """Silence FFmpeg's and OpenCV's own log lines (e.g. "moov atom not found") unless
    `verbose`: a bad video must give one line, ours. OpenCV reads OPENCV_FFMPEG_LOGLEVEL
    when it first loads FFmpeg; -8 is AV_LOG_QUIET. A value the user set is kept."""
    if verbose:
        yield
        return
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(level)


@contextlib.contextmanager
def open_video(path: Path) -> Iterator[cv2.VideoCapture]:
    """An FFmpeg capture that rotates frames upright by the display rotation; VideoError if
    the file cannot be opened."""
    path = Path(path)
    if not path.is_file():
        raise VideoError(f"video {path} does not exist")
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    try:
        if not cap.isOpened():
            raise VideoError(f"cannot read video {path} (corrupt, truncated or not a video)")
        cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)  # phones store portrait video sideways
        yield cap
    finally:
        cap.release()


def probe(cap: cv2.VideoCapture, path: Path) -> VideoInfo:
    fourcc = int(cap.get(cv2.CAP_PROP_FOURCC))
    codec = "".join(chr((fourcc >> (8 * i)) & 0xFF) for i in range(4)).strip("\0 ")
    rotation = round(cap.get(cv2.CAP_PROP_ORIENTATION_META)) % 360
    # with CAP_PROP_ORIENTATION_AUTO, OpenCV already reports the rotated (upright) size
    w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    return VideoInfo(
        Path(path),
        max(0, int(cap.get(cv2.CAP_PROP_FRAME_COUNT))),
        max(0.0, float(cap.get(cv2.CAP_PROP_FPS))),
        w,
        h,
        rotation,
        codec,
    )


def decoded(cap: cv2.VideoCapture) -> Iterator[np.ndarray]:
    """Every frame (H, W, 3) uint8 BGR, in order, until the stream ends or stops decoding."""
    while True:
        ok, frame = cap.read()
        if not ok or frame is None:
            return
        yield frame


def write_png(path: Path, bgr: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise OSError(f"could not encode frame {path.name}")
    path.write_bytes(buf.tobytes())


def scan_video(
    path: Path, bounds: np.ndarray | None, out_dir: Path, stem: str, progress: Progress
) -> tuple[np.ndarray, list[int]]:
    """Decode every frame once -> ((N,) sharpness, frames written). With `bounds`, the
    sharpest frame of each window is written to `out_dir` when its window ends."""
    scores: list[float] = []
    written: list[int] = []
    window, best, best_score = 0, None, -1.0
    with open_video(path) as cap:
        total = probe(cap, path).frames_announced or None
        for i, frame in enumerate(decoded(cap)):
            score = frame_sharpness(frame)
            scores.append(score)
            if bounds is not None and window < len(bounds) - 1:
                if score > best_score:
                    best, best_score = (i, frame), score
                if i + 1 == bounds[window + 1]:
                    write_png(out_dir / frame_name(stem, best[0]), best[1])
                    written.append(best[0])
                    window, best, best_score = window + 1, None, -1.0
            progress(f"decoding {path.name}", i + 1, total)
    return np.array(scores, dtype=np.float64), written


def write_frames(
    path: Path, indices: np.ndarray, out_dir: Path, stem: str, progress: Progress
) -> None:
    """Decode `path` again and write the frames at `indices` as `<stem>_<index>.png`."""
    wanted = {int(i) for i in indices}
    last = max(wanted, default=-1)
    with open_video(path) as cap:
        for i, frame in enumerate(decoded(cap)):
            if i in wanted:
                write_png(out_dir / frame_name(stem, i), frame)
                wanted.discard(i)
            progress(f"writing frames of {path.name}", i + 1, last + 1)
            if i >= last:
                break
    if wanted:
        raise VideoError(
            f"video {path} decoded differently the second time (frame {min(wanted)} "
            "is missing): is it still being written?"
        )


def extract_video(
    path: Path, out_dir: Path, stem: str, budget: int, config: VideoConfig, progress: Progress
) -> VideoFrames:
    """Choose and write the frames of one video (`budget` windows, or per --fps)."""
    with open_video(path) as cap:
        info = probe(cap, path)

    def windows(n: int) -> int:
        return windows_for(n, info.fps, budget, config.fps)

    announced = info.frames_announced
    provisional = window_bounds(announced, windows(announced)) if announced > 0 else None
    scores, written = scan_video(path, provisional, out_dir, stem, progress)
    if len(scores) == 0:
        raise VideoError(f"video {path} has no decodable frames")
    bounds = window_bounds(len(scores), windows(len(scores)))
    chosen = sharpest_in_windows(scores, bounds)
    passes = 1
    if len(scores) != announced or written != chosen.tolist():
        for i in written:
            (out_dir / frame_name(stem, i)).unlink()
        write_frames(path, chosen, out_dir, stem, progress)
        passes = 2
    threshold = blur_threshold(scores[chosen], config.blur_ratio)
    for i in chosen[scores[chosen] < threshold]:
        (out_dir / frame_name(stem, int(i))).unlink()
    return VideoFrames(info, stem, scores, bounds, chosen, threshold, config.blur_ratio, passes)


def unique_stems(paths: list[Path]) -> list[str]:
    """Frame prefixes of the videos: the stem, or stem_suffix when two videos share a stem."""
    stems = [frame_stem(p.name) for p in paths]
    return [
        frame_stem(p.name.replace(".", "_")) if stems.count(s) > 1 else s
        for p, s in zip(paths, stems)
    ]


def extract_videos(
    paths: list[Path], out_dir: Path, config: VideoConfig, progress: Progress, verbose: bool = False
) -> list[VideoFrames]:
    """Frames of every video into `out_dir`; --frames is shared by duration (`frame_budgets`)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    with quiet_decoder(verbose):
        infos = []
        for p in paths:
            with open_video(p) as cap:
                infos.append(probe(cap, p))
        durations = [i.frames_announced / i.fps if i.fps > 0 else i.frames_announced for i in infos]
        budgets = frame_budgets(np.array(durations), config.frames)
        return [
            extract_video(p, out_dir, stem, int(b), config, progress)
            for p, stem, b in zip(paths, unique_stems(paths), budgets)
        ]


def video_report(video: VideoFrames) -> dict:
    """Plain JSON: the video, the frames kept, and each dropped frame (or window's worth of
    frames) with the reason."""
    info, scores, chosen = video.info, video.scores, video.chosen
    fps = info.fps

    def frame(i: int) -> dict:
        out = {
            "frame": i,
            "name": frame_name(video.stem, i),
            "sharpness": round(float(scores[i]), 2),
        }
        return {**out, "time_s": round(i / fps, 3)} if fps > 0 else out

    median = float(np.median(scores[chosen]))
    dropped = []
    for (start, end), c in zip(zip(video.bounds[:-1], video.bounds[1:]), chosen.tolist()):
        if scores[c] < video.threshold:
            dropped.append(
                {
                    **frame(c),
                    "reason": (
                        f"blurred: Laplacian variance {scores[c]:.1f} < {video.blur_ratio:g} x median "
                        f"{median:.1f}"
                    ),
                }
            )
        if end - start > 1:
            dropped.append(
                {
                    "frames": [int(start), int(end) - 1],
                    "count": int(end - start - 1),
                    "reason": f"not the sharpest of its window (frame {c} is)",
                }
            )
    notes = []
    if info.frames_announced != len(scores):
        notes.append(
            f"decoded {len(scores)} frames, the container announces "
            f"{info.frames_announced} (truncated file or estimated count)"
        )
    return {
        "video": info.path.name,
        "path": str(info.path.resolve()),
        "codec": info.codec,
        "fps": round(fps, 3),
        "width": info.width,
        "height": info.height,
        "rotation_deg": info.rotation_deg,
        "frames_announced": info.frames_announced,
        "frames_decoded": len(scores),
        "windows": len(chosen),
        "frames_kept": len(video.kept),
        "decoding_passes": video.passes,
        "sharpness": {
            "measure": "variance of the Laplacian of luma",
            "measured_at": list(measure_size(info.width, info.height)),
            "median_of_chosen": round(median, 2),
            "min": round(float(scores.min()), 2),
            "max": round(float(scores.max()), 2),
            "blur_threshold": round(video.threshold, 2),
        },
        "kept": [frame(int(i)) for i in video.kept],
        "dropped": dropped,
        "notes": notes,
    }
