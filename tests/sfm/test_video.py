"""Frame choice for video input (recon/sfm/video.py): the Laplacian-variance sharpness against
a worked example and a brute-force stencil, window layout and per-window argmax against
brute force, blur rejection on a synthetic sequence with known blurred frames, budgets."""

from itertools import pairwise

import cv2
import numpy as np
import pytest

from recon.sfm.video import (
    VideoConfig,
    blur_threshold,
    frame_budgets,
    frame_name,
    frame_sharpness,
    frame_stem,
    is_video,
    laplacian_variance,
    measure_size,
    sharpest_in_windows,
    validate_video_config,
    window_bounds,
    windows_for,
)


def texture(h: int = 120, w: int = 160, seed: int = 0) -> np.ndarray:
    """(h, w, 3) uint8 BGR of 4x4-pixel random blocks: plenty of edges at every scale."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, size=(h // 4, w // 4, 3), dtype=np.uint8)
    return np.kron(small, np.ones((4, 4, 1), dtype=np.uint8))


def laplacian_variance_brute(grey: np.ndarray) -> float:
    """The 4-neighbour stencil written out, borders mirrored without the edge pixel."""
    p = np.pad(np.asarray(grey, np.float64), 1, mode="reflect")
    lap = p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:] - 4 * p[1:-1, 1:-1]
    return float(np.mean((lap - lap.mean()) ** 2))


def test_laplacian_variance_impulse_worked_example():
    # one pixel of 1 away from the border: L = -4 there, +1 at 4 neighbours, 0 elsewhere
    # -> mean 0, variance (16 + 4) / (H W)
    grey = np.zeros((7, 9))
    grey[3, 4] = 1.0
    assert laplacian_variance(grey) == pytest.approx(20 / 63, rel=1e-12)
    assert laplacian_variance(np.full((5, 6), 0.7)) == pytest.approx(0.0, abs=1e-20)


def test_laplacian_variance_matches_brute_force_stencil():
    rng = np.random.default_rng(3)
    for shape in [(1, 1), (2, 3), (17, 11), (64, 48)]:
        grey = rng.normal(size=shape) * 50
        assert laplacian_variance(grey) == pytest.approx(laplacian_variance_brute(grey), rel=1e-10)


def test_measure_size_downscales_the_longer_side_only():
    assert measure_size(1920, 1080) == (960, 540)
    assert measure_size(1080, 1920) == (540, 960)
    assert measure_size(200, 100) == (200, 100)  # never upscaled
    assert measure_size(4000, 3000, side=1000) == (1000, 750)


def test_sharpness_falls_with_blur_and_ignores_colour_only_changes():
    frame = texture()
    scores = [
        frame_sharpness(frame if s == 0 else cv2.GaussianBlur(frame, (0, 0), s))
        for s in (0, 0.7, 1.5, 3, 6)
    ]
    assert all(a > b for a, b in pairwise(scores))
    assert scores[-1] < 0.05 * scores[0]
    # measured on luma: the same luma in another colour scores the same
    grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    assert frame_sharpness(frame) == pytest.approx(frame_sharpness(grey), rel=1e-12)
    # a frame larger than the measuring size is measured downscaled: a 2x nearest upscale of
    # a 960 px frame measures like the frame itself (area averaging undoes it exactly)
    big = texture(480, 960, seed=1)
    up = cv2.resize(big, (1920, 960), interpolation=cv2.INTER_NEAREST)
    assert frame_sharpness(up) == pytest.approx(frame_sharpness(big), rel=1e-6)


def test_window_bounds_worked_example_and_layout():
    assert window_bounds(10, 3).tolist() == [0, 3, 6, 10]
    assert window_bounds(5, 9).tolist() == [0, 1, 2, 3, 4, 5]  # more windows than frames
    assert window_bounds(4, 0).tolist() == [0, 4]
    for n in range(1, 40):
        for k in range(1, n + 1):
            b = window_bounds(n, k)
            sizes = np.diff(b)
            assert b[0] == 0 and b[-1] == n and len(sizes) == k
            assert sizes.min() >= 1 and sizes.max() - sizes.min() <= 1
    with pytest.raises(ValueError):
        window_bounds(0, 3)


def test_sharpest_in_windows_worked_example_ties_and_brute_force():
    scores = np.array([1, 5, 2, 3, 3, 9, 4, 0, 1])
    assert sharpest_in_windows(scores, np.array([0, 3, 6, 9])).tolist() == [1, 5, 6]
    assert sharpest_in_windows(np.array([2, 2, 1]), np.array([0, 3])).tolist() == [0]  # first
    rng = np.random.default_rng(0)
    for _ in range(50):
        n = int(rng.integers(1, 60))
        scores = rng.random(n)
        bounds = window_bounds(n, int(rng.integers(1, n + 1)))
        brute = [max(range(s, e), key=lambda i: scores[i]) for s, e in pairwise(bounds)]
        assert sharpest_in_windows(scores, bounds).tolist() == brute


SHARP_AT = [1, 3, 7, 9, 13, 16, 19, 23]  # the one sharp frame of each window of 3
PAN_WINDOWS = (2, 6)  # windows whose frames are all blurred


def pan_sequence(h: int = 200, w: int = 320) -> list[np.ndarray]:
    """24 frames of a slowly panning texture, meant as 8 windows of 3. Every window has one
    sharp frame (SHARP_AT) between slightly blurred ones (sigma 1 px), except PAN_WINDOWS,
    shot "during a fast pan": their frames are blurred with sigma 2, 3, 4 px."""
    base = texture(h, w, seed=5)
    frames = []
    for i in range(24):
        view = np.roll(base, 2 * i, axis=1)  # a 2 px pan per frame
        if i // 3 in PAN_WINDOWS:
            view = cv2.GaussianBlur(view, (0, 0), 2.0 + (i % 3))
        elif i not in SHARP_AT:
            view = cv2.GaussianBlur(view, (0, 0), 1.0)
        frames.append(view)
    return frames


# per window: the sharp frame, or the least blurred (sigma 2) first frame of a pan window
EXPECTED_CHOSEN = [SHARP_AT[w] if w not in PAN_WINDOWS else 3 * w for w in range(8)]
EXPECTED_DROPPED = [3 * w for w in PAN_WINDOWS]


def test_synthetic_sequence_blurred_windows_are_dropped():
    """Window selection picks the known sharp frames; the blur test drops exactly the best
    frames of the pan windows."""
    scores = np.array([frame_sharpness(f) for f in pan_sequence()])
    chosen = sharpest_in_windows(scores, window_bounds(len(scores), 8))
    assert chosen.tolist() == EXPECTED_CHOSEN
    threshold = blur_threshold(scores[chosen], VideoConfig().blur_ratio)
    dropped = chosen[scores[chosen] < threshold]
    assert dropped.tolist() == EXPECTED_DROPPED
    # the numbers behind it: blurred windows' best is far under the ratio, sharp ones far above
    sharp_scores = scores[[c for w, c in enumerate(chosen) if w not in PAN_WINDOWS]]
    assert sharp_scores.min() > 2 * threshold and scores[dropped].max() < 0.5 * threshold


def test_blur_threshold_never_drops_most_frames():
    # at most half the values lie strictly below their median, so at most half are dropped
    rng = np.random.default_rng(2)
    for _ in range(100):
        chosen = rng.exponential(size=int(rng.integers(1, 30))) ** 3
        assert np.sum(chosen < blur_threshold(chosen, 0.99)) <= len(chosen) // 2
    assert blur_threshold(np.array([10.0, 20.0, 40.0]), 0.35) == pytest.approx(7.0)
    assert blur_threshold(np.array([10.0, 20.0]), 0.0) == 0.0


def test_windows_for_frames_and_fps():
    assert windows_for(300, 30.0, frames=40, fps=0) == 40
    assert windows_for(300, 30.0, frames=1000, fps=0) == 300  # never more windows than frames
    assert windows_for(300, 30.0, frames=0, fps=2.0) == 20  # 10 s at 2 frames per second
    assert windows_for(300, 29.97, frames=0, fps=2.0) == 20  # round(20.02)
    assert windows_for(10, 30.0, frames=0, fps=0.5) == 1  # at least one
    with pytest.raises(ValueError, match="frame rate"):
        windows_for(300, 0.0, frames=0, fps=2.0)


def test_frame_budgets_worked_examples():
    assert frame_budgets(np.array([10.0, 30.0]), 8).tolist() == [2, 6]
    assert frame_budgets(np.array([1.0, 1.0, 1.0]), 4).tolist() == [2, 1, 1]
    assert frame_budgets(np.array([1.0, 99.0]), 10).tolist() == [1, 10]  # each video gets one
    assert frame_budgets(np.array([5.0]), 100).tolist() == [100]
    assert frame_budgets(np.array([0.0, 0.0]), 5).tolist() == [3, 2]  # no durations: evenly
    rng = np.random.default_rng(1)
    for _ in range(50):
        d = rng.random(int(rng.integers(1, 6))) + 0.01
        total = int(rng.integers(len(d), 200))
        b = frame_budgets(d, total)
        assert b.min() >= 1 and total <= b.sum() <= total + len(d)
        assert np.all(np.abs(b - total * d / d.sum()) <= 1 + 1e-9)


def test_names_suffixes_and_config_validation():
    assert frame_name("clip", 123) == "clip_000123.png"
    assert sorted(frame_name("a", i) for i in (10, 9, 100)) == [
        "a_000009.png",
        "a_000010.png",
        "a_000100.png",
    ]
    assert frame_stem("my walk.MOV") == "my_walk" and frame_stem("noext") == "noext"
    assert is_video("IMG_0001.MOV") and is_video("x.webm") and not is_video("x.jpg")
    assert not is_video("x.wmv")
    validate_video_config(VideoConfig())
    validate_video_config(VideoConfig(frames=0, fps=2.0))
    for bad, match in [
        (VideoConfig(frames=10, fps=2.0), "exactly one"),
        (VideoConfig(frames=0), "exactly one"),
        (VideoConfig(frames=-1), "positive"),
        (VideoConfig(blur_ratio=1.0), "blur-ratio"),
    ]:
        with pytest.raises(ValueError, match=match):
            validate_video_config(bad)
