"""Choosing the frames of a video for SfM: sharpness, windows, blur rejection, frame budgets.

Pure functions (arrays in, arrays out). A video of N frames is split into K windows, one per
wanted frame; each window keeps its sharpest frame, and a kept frame is dropped when it is
still far blurrier than the other windows' sharpest frames (a whole window shot during a
fast pan).
Sharpness is the variance of the Laplacian (Pech-Pacheco et al. 2000, "Diatom autofocusing in
brightfield microscopy: a comparative study", ICPR, the "VAR of Laplacian" measure): blur
removes high spatial frequencies, and the Laplacian (a high-pass filter) keeps little else.
Decoding and writing frames lives in `video_extract`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import cv2
import numpy as np

from recon.options import opt

# Containers whose usual codecs (H.264, HEVC, VP8/9, AV1, MPEG-4, MJPEG, ProRes) the FFmpeg
# bundled with opencv-python 4.14 decodes (each checked by decoding a file ffmpeg wrote).
VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")

# Sharpness is measured on the grey frame area-downscaled to this longer side. On the 67 fox
# phone photos (1080x1920), measured at 960 px, the sharp photos span 0.46-2.3x their median
# while a Gaussian blur of sigma = 2 px (full resolution) brings every photo under 0.30x the
# sharp median (sigma = 1 px: median 0.46x): the blur SIFT cares about still separates, and
# the measure costs ~1 ms instead of ~5 ms at full size. Downscaling also averages away the
# sensor noise and compression artefacts a full-size Laplacian would mostly measure.
MEASURE_SIDE = 960


@dataclass(frozen=True)
class VideoConfig:
    """How frames are taken from videos (one CLI flag each; the comment is its help).

    Default 100 frames: with the sequential matcher 100 frames make ~2,000 pairs, about what
    the 67-photo fox capture costs exhaustively (2,211 pairs, SfM 111 s on this 2-core CPU);
    nerfstudio's 300 makes ~4,800 pairs, 3x the SIFT work and a mapper with 3x the images, and
    training holds every image as float32 (1080x1920: 25 MB each, 7.5 GB for 300).

    Blur ratio 0.35: on the fox photos (see MEASURE_SIDE) sharp views of one capture lie at
    0.46x their median or above, and a Gaussian blur of sigma = 2 px puts every photo under
    0.30x; 0.35 sits in that gap, so content alone never drops a frame and a window shot
    with ~2 px of blur or more does (sigma = 1 px: 13 % of the photos would be dropped).
    """

    frames: int = opt(100, "about this many frames in all, evenly over the video(s) (0 with --fps)")
    fps: float = opt(0.0, "instead of --frames: this many frames per second of video (0: unused)")
    blur_ratio: float = opt(
        0.35, "drop a chosen frame whose sharpness is under this x the chosen frames' median"
    )


def validate_video_config(config: VideoConfig) -> None:
    """One-line ValueError for a config that cannot choose frames."""
    if config.frames < 0 or config.fps < 0:
        raise ValueError(
            f"--frames and --fps must be positive, got {config.frames} and {config.fps:g}"
        )
    if (config.frames > 0) == (config.fps > 0):
        raise ValueError("give exactly one of --frames N (N > 0) or --fps F (F > 0)")
    if not 0.0 <= config.blur_ratio < 1.0:
        raise ValueError(f"--blur-ratio must be in [0, 1), got {config.blur_ratio}")


def is_video(name: str) -> bool:
    """True for a file name with one of VIDEO_SUFFIXES (any case: phones write .MOV)."""
    return any(name.lower().endswith(s) for s in VIDEO_SUFFIXES)


def laplacian_variance(grey: np.ndarray) -> float:
    """Var[L], L = d2I/dx2 + d2I/dy2 by the 3x3 stencil [[0, 1, 0], [1, -4, 1], [0, 1, 0]],
    borders mirrored without repeating the edge pixel (cv2's default, numpy's "reflect").

    grey: (H, W), any real dtype. Example: one pixel of value 1 on a 0 image, away from the
    border, gives L = -4 there and +1 at its 4 neighbours: mean 0, Var = (16 + 4) / (H W).
    """
    lap = cv2.Laplacian(np.asarray(grey, np.float64), cv2.CV_64F, ksize=1)
    return float(lap.var())


def measure_size(width: int, height: int, side: int = MEASURE_SIDE) -> tuple[int, int]:
    """(w, h) with the longer side scaled down to `side` (never up), aspect ratio kept."""
    scale = min(1.0, side / max(width, height))
    return max(1, round(width * scale)), max(1, round(height * scale))


def frame_sharpness(bgr: np.ndarray, side: int = MEASURE_SIDE) -> float:
    """Laplacian variance of a frame's luma, area-downscaled to `side` px (see MEASURE_SIDE).

    bgr: (H, W, 3) uint8 as decoded. Luma (Rec. 601 weights) because blur is a luminance
    property and video stores chroma at half resolution (4:2:0), which would dilute it.
    """
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY) if bgr.ndim == 3 else bgr
    w, h = measure_size(grey.shape[1], grey.shape[0], side)
    if (w, h) != (grey.shape[1], grey.shape[0]):
        grey = cv2.resize(grey, (w, h), interpolation=cv2.INTER_AREA)
    return laplacian_variance(grey.astype(np.float32))


def window_bounds(num_frames: int, num_windows: int) -> np.ndarray:
    """(K + 1,) int: window k holds frames bounds[k] <= i < bounds[k + 1], bounds[k] =
    floor(k N / K); windows differ in length by at most one frame. K is clamped to [1, N].

    Example: N = 10, K = 3 -> [0, 3, 6, 10].
    """
    if num_frames < 1:
        raise ValueError("a video needs at least one frame to split into windows")
    k = min(max(1, num_windows), num_frames)
    return (np.arange(k + 1, dtype=np.int64) * num_frames) // k


def sharpest_in_windows(scores: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """(K,) int: the index of the largest score in each window (the first one on ties).

    scores: (N,) sharpness per frame; bounds: (K + 1,) from `window_bounds`.
    Example: scores [1, 5, 2, 3, 3, 9, 4, 0, 1], bounds [0, 3, 6, 9] -> [1, 5, 6].
    """
    scores = np.asarray(scores, dtype=np.float64)
    starts, ends = bounds[:-1], bounds[1:]
    return np.array([s + int(np.argmax(scores[s:e])) for s, e in zip(starts, ends)], np.int64)


def blur_threshold(chosen_scores: np.ndarray, ratio: float) -> float:
    """ratio x the median sharpness of the frames chosen (one per window).

    Relative, because the Laplacian variance depends on content and resolution and has no
    absolute "sharp" value; over the chosen frames, because they are what each stretch of the
    video can offer at best, so a window whose best is far below the others' best was shot
    during a fast pan or a focus hunt. At most half the chosen frames lie below their
    median, so the threshold (ratio < 1) never drops most of a video.
    """
    return float(ratio * np.median(np.asarray(chosen_scores, dtype=np.float64)))


def windows_for(num_frames: int, video_fps: float, frames: int, fps: float) -> int:
    """Number of windows of one video: `frames` (this video's budget), or with `fps` > 0 one
    per 1/fps seconds of video, round(N fps / video_fps); always within [1, N]."""
    if fps > 0:
        if video_fps <= 0:
            raise ValueError(
                "the video does not state its frame rate: use --frames instead of --fps"
            )
        wanted = round(num_frames * fps / video_fps)
    else:
        wanted = frames
    return int(min(max(1, wanted), max(1, num_frames)))


def frame_budgets(durations: np.ndarray, total: int) -> np.ndarray:
    """(V,) int: `total` frames shared among V videos in proportion to their durations
    (largest-remainder rounding); a video that would get none gets one, so the sum is `total`
    plus the number of such videos.

    Example: durations [10, 30] s, total 8 -> [2, 6]; [1, 1, 1], 4 -> [2, 1, 1].
    """
    durations = np.asarray(durations, dtype=np.float64)
    v = len(durations)
    if v == 0:
        return np.zeros(0, np.int64)
    weight = durations / durations.sum() if durations.sum() > 0 else np.full(v, 1.0 / v)
    exact = total * weight
    budget = np.floor(exact).astype(np.int64)
    order = np.argsort(-(exact - budget), kind="stable")
    budget[order[: total - int(budget.sum())]] += 1
    return np.maximum(budget, 1)


def frame_stem(video_name: str) -> str:
    """Prefix of a video's frame files: its stem with whitespace as "_" (COLMAP's pair lists
    are space-separated)."""
    stem = video_name.rsplit(".", 1)[0] if "." in video_name else video_name
    return re.sub(r"\s", "_", stem)


def frame_name(stem: str, index: int) -> str:
    """`<stem>_000123.png`: the frame's index in the video, zero-padded so names sort in
    capture order (sequential matching pairs neighbours by name)."""
    return f"{stem}_{index:06d}.png"
