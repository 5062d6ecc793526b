"""Photo validation and staging on tiny generated files: bad folders, corrupt and non-image
files, duplicates, EXIF rotation, 16-bit and grayscale PNGs, content sniffing."""

import cv2
import numpy as np
import pytest
from PIL import Image

from recon.sfm.photos import (
    EXIF_ORIENTATION_TAG,
    PhotoError,
    bits_per_sample,
    png_bit_depth,
    prepare_photos,
)


def blocks(h: int, w: int, seed: int = 0) -> np.ndarray:
    """(h, w, 3) uint8 of 8x8-pixel random colour blocks: survives JPEG compression."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, size=(h // 8, w // 8, 3), dtype=np.uint8)
    return np.kron(small, np.ones((8, 8, 1), dtype=np.uint8))


def save(path, array, **kwargs):
    Image.fromarray(array).save(path, **kwargs)
    return path


def folder_with(tmp_path, n: int = 2):
    src = tmp_path / "photos"
    src.mkdir()
    for i in range(n):
        save(src / f"img{i}.png", blocks(96, 128, seed=i))
    return src


def test_missing_and_empty_folder(tmp_path):
    with pytest.raises(PhotoError, match="does not exist"):
        prepare_photos(tmp_path / "nope", tmp_path / "stage")
    (tmp_path / "empty").mkdir()
    with pytest.raises(PhotoError, match="is empty") as info:
        prepare_photos(tmp_path / "empty", tmp_path / "stage")
    assert isinstance(info.value, ValueError) and "\n" not in str(info.value)


def test_no_images_and_single_image(tmp_path):
    src = tmp_path / "photos"
    src.mkdir()
    (src / "notes.txt").write_text("not a photo")
    with pytest.raises(PhotoError, match="no usable images"):
        prepare_photos(src, tmp_path / "stage")
    save(src / "only.png", blocks(96, 128))
    with pytest.raises(PhotoError, match="only 1 usable image .*only.png"):
        prepare_photos(src, tmp_path / "stage")


def test_good_photos_are_symlinked(tmp_path):
    src = folder_with(tmp_path)
    gray = save(src / "gray.png", blocks(96, 128)[..., 0])
    photos = prepare_photos(src, tmp_path / "stage")
    assert photos.names == ["gray.png", "img0.png", "img1.png"]
    assert photos.skipped == ()
    staged = tmp_path / "stage" / "gray.png"
    assert staged.is_symlink() and staged.resolve() == gray.resolve()
    assert all(p.converted == "" for p in photos.photos)
    assert (photos.photos[0].width, photos.photos[0].height, photos.photos[0].mode) == (
        128,
        96,
        "L",
    )


def test_corrupt_nonimage_small_and_duplicate_are_listed(tmp_path):
    src = folder_with(tmp_path)
    jpeg = save(tmp_path / "full.jpg", blocks(96, 128, seed=5), quality=90).read_bytes()
    (src / "truncated.jpg").write_bytes(jpeg[: len(jpeg) // 2])
    (src / "fake.jpg").write_text("this is text with a .jpg name")
    save(src / "thumb.png", blocks(32, 48))
    (src / "z_copy.png").write_bytes((src / "img0.png").read_bytes())
    photos = prepare_photos(src, tmp_path / "stage", min_side=64)
    assert photos.names == ["img0.png", "img1.png"]
    reasons = dict(photos.skipped)
    assert reasons["z_copy.png"] == "duplicate of img0.png"  # the first in name order is kept
    assert reasons["fake.jpg"].startswith("not an image")
    assert reasons["truncated.jpg"].startswith("unreadable")
    assert reasons["thumb.png"].startswith("too small (48x32")
    assert not (tmp_path / "stage" / "truncated.jpg").exists()


def test_exif_rotation_is_applied(tmp_path):
    """Orientation 6 = rotate 90 deg clockwise for display: the staged copy is upright."""
    src = folder_with(tmp_path)
    stored = blocks(96, 160, seed=3)
    exif = Image.Exif()
    exif[EXIF_ORIENTATION_TAG] = 6
    save(src / "phone.jpg", stored, quality=95, exif=exif.tobytes())
    photos = prepare_photos(src, tmp_path / "stage")
    phone = next(p for p in photos.photos if p.name == "phone.jpg")
    assert (phone.width, phone.height) == (96, 160)
    assert phone.converted == "EXIF rotation applied"
    staged = Image.open(tmp_path / "stage" / "phone.jpg")
    assert not (tmp_path / "stage" / "phone.jpg").is_symlink()
    assert staged.getexif().get(EXIF_ORIENTATION_TAG, 1) == 1
    decoded = np.asarray(Image.open(src / "phone.jpg"), dtype=float)  # Pillow does not rotate
    staged = np.asarray(staged, dtype=float)
    assert np.abs(staged - np.rot90(decoded, k=-1)).mean() < 8.0  # clockwise, one JPEG generation
    assert np.abs(staged - np.rot90(decoded, k=1)).mean() > 30.0


def test_16bit_png_is_converted_to_8bit(tmp_path):
    src = folder_with(tmp_path)
    ramp = (np.arange(96 * 128, dtype=np.uint32).reshape(96, 128) * 5).astype(np.uint16)
    cv2.imwrite(str(src / "deep_gray.png"), ramp)
    rgb16 = (blocks(96, 128, seed=9).astype(np.uint16) * 257 + 100).astype(np.uint16)
    cv2.imwrite(str(src / "deep_rgb.png"), rgb16)  # written BGR, read back BGR below
    cv2.imwrite(str(src / "deep_rgb.tif"), rgb16)
    assert png_bit_depth(src / "deep_gray.png") == 16 and png_bit_depth(src / "img0.png") == 8
    assert bits_per_sample(src / "deep_rgb.tif") == 16 and bits_per_sample(src / "img1.png") == 8
    photos = prepare_photos(src, tmp_path / "stage")
    converted = {p.name: p.converted for p in photos.photos}
    assert (
        converted["deep_gray.png"] == converted["deep_rgb.png"] == "16-bit PNG converted to 8 bit"
    )
    gray8 = cv2.imread(str(tmp_path / "stage" / "deep_gray.png"), cv2.IMREAD_UNCHANGED)
    assert gray8.dtype == np.uint8
    np.testing.assert_allclose(gray8, ramp / 257.0, atol=1.0)
    rgb8 = cv2.imread(str(tmp_path / "stage" / "deep_rgb.png"), cv2.IMREAD_UNCHANGED)
    assert rgb8.dtype == np.uint8 and rgb8.shape == (96, 128, 3)
    np.testing.assert_allclose(rgb8, rgb16 / 257.0, atol=1.0)
    tif8 = cv2.imread(str(tmp_path / "stage" / "deep_rgb.tif"), cv2.IMREAD_UNCHANGED)
    assert tif8.dtype == np.uint8
    np.testing.assert_allclose(tif8, rgb16 / 257.0, atol=1.0)


def test_format_is_sniffed_by_content(tmp_path):
    """A JPEG without an extension and a BMP are used; COLMAP gets names it can read."""
    src = folder_with(tmp_path)
    save(src / "IMG_0001", blocks(96, 128, seed=7), format="JPEG", quality=95)
    save(src / "scan.bmp", blocks(96, 128, seed=8))
    save(src / "my photo 1.png", blocks(96, 128, seed=12))
    photos = prepare_photos(src, tmp_path / "stage")
    by_source = {p.source.name: p for p in photos.photos}
    assert by_source["IMG_0001"].name == "IMG_0001.jpg"
    assert by_source["scan.bmp"].name == "scan.bmp.png"
    assert by_source["my photo 1.png"].name == "my_photo_1.png"  # COLMAP pair lists split on spaces
    assert (tmp_path / "stage" / "my_photo_1.png").is_symlink()
    assert Image.open(tmp_path / "stage" / "IMG_0001.jpg").format == "JPEG"
    bmp = np.asarray(Image.open(tmp_path / "stage" / "scan.bmp.png"))
    np.testing.assert_array_equal(bmp, blocks(96, 128, seed=8))
    # A second source that would be staged under the same name is refused, not overwritten.
    save(src / "IMG_0001.jpg", blocks(96, 128, seed=11), quality=95)
    clash = prepare_photos(src, tmp_path / "stage2")
    assert dict(clash.skipped) == {
        "IMG_0001.jpg": "staged name IMG_0001.jpg is taken by another photo"
    }
