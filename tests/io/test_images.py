"""Image writing: PNG exact at any compression, JPEG within its quantisation, RGBA kept."""

import cv2
import numpy as np

from recon.io.images import read_image, write_jpeg, write_png


def _gradient(h=24, w=32, channels=3):
    y, x = np.mgrid[0:h, 0:w]
    planes = [x / (w - 1), y / (h - 1), (x + y) / (w + h - 2), np.full((h, w), 0.5)]
    return np.stack(planes[:channels], -1).astype(np.float32)


def test_png_round_trips_exactly_at_any_compression(tmp_path):
    rgba = _gradient(channels=4)
    expected = np.floor(rgba * 255 + 0.5).astype(np.uint8)  # round half up
    for level in (None, 0, 9):
        path = tmp_path / f"c{level}.png"
        write_png(path, rgba, compression=level)
        back = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA)
        np.testing.assert_array_equal(back, expected)
    sizes = [(tmp_path / f"c{level}.png").stat().st_size for level in (0, 9)]
    assert sizes[1] < sizes[0]  # 9 compresses, 0 stores


def test_jpeg_keeps_a_smooth_image_within_its_quantisation(tmp_path):
    rgb = _gradient()
    write_jpeg(tmp_path / "g.jpg", rgb, quality=95)
    back = read_image(tmp_path / "g.jpg")
    assert back.shape == rgb.shape
    error = np.abs(back - rgb)  # chroma subsampling: a few levels at the colour edges
    assert error.mean() < 2 / 255 and error.max() < 10 / 255
    assert np.abs(back[..., ::-1] - rgb).mean() > 0.05  # the channels are not swapped
