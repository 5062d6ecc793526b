"""Bad photo folders. The validation layer (recon/sfm/photos.py) directly for the
per-file cases not in tests/sfm/test_photos.py (a 1-pixel image, mixed sizes, textureless
photos pass validation), and the real `recon sfm PHOTOS` for whole folders that cannot work:
one error line, a non-zero exit, and no workspace left behind."""

import numpy as np
import pytest
from PIL import Image

from recon.sfm.photos import PhotoError, prepare_photos
from tests.conftest import recon_cli
from tests.hard_cases.conftest import assert_one_line_error


def blocks(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.kron(
        rng.integers(0, 256, size=(h // 8, w // 8, 3), dtype=np.uint8), np.ones((8, 8, 1), np.uint8)
    )


def test_one_pixel_image_is_skipped_with_its_size(tmp_path):
    src = tmp_path / "photos"
    src.mkdir()
    for i in range(2):
        Image.fromarray(blocks(96, 128, i)).save(src / f"img{i}.png")
    Image.fromarray(np.zeros((1, 1, 3), np.uint8)).save(src / "dot.png")
    photos = prepare_photos(src, tmp_path / "stage")
    assert photos.names == ["img0.png", "img1.png"]
    assert dict(photos.skipped)["dot.png"].startswith("too small (1x1")


def test_mixed_sizes_and_textureless_photos_are_all_kept_with_their_own_sizes(tmp_path):
    """Validation does not judge texture or size consistency: SfM groups cameras by size
    (tests/sfm/test_colmap_sfm.py::test_camera_groups_split_mixed_sizes) and reports textureless
    photos by name (::test_blank_photos_raise_one_line_sfm_error)."""
    src = tmp_path / "photos"
    src.mkdir()
    Image.fromarray(blocks(96, 128, 0)).save(src / "a.png")
    Image.fromarray(blocks(128, 96, 1)).save(src / "b.png")
    Image.fromarray(blocks(480, 640, 2)).save(src / "c.jpg", quality=90)
    Image.fromarray(np.full((96, 128, 3), 128, np.uint8)).save(src / "flat.png")
    photos = prepare_photos(src, tmp_path / "stage")
    assert photos.names == ["a.png", "b.png", "c.jpg", "flat.png"]
    assert [(p.width, p.height) for p in photos.photos] == [
        (128, 96),
        (96, 128),
        (640, 480),
        (128, 96),
    ]


def truncated_jpeg_and_a_dot(src):
    Image.fromarray(blocks(96, 128, 3)).save(src / "full.jpg", quality=90)
    data = (src / "full.jpg").read_bytes()
    (src / "full.jpg").write_bytes(data[: len(data) // 2])
    Image.fromarray(np.zeros((1, 1, 3), np.uint8)).save(src / "dot.png")
    (src / "notes.txt").write_text("not a photo")


def single_image(src):
    Image.fromarray(blocks(96, 128, 4)).save(src / "only.png")


def test_a_folder_of_one_photo_and_its_duplicate_is_refused(tmp_path):
    src = tmp_path / "photos"
    src.mkdir()
    Image.fromarray(blocks(96, 128, 5)).save(src / "a.png")
    (src / "b.png").write_bytes((src / "a.png").read_bytes())
    with pytest.raises(
        PhotoError, match=r"only 1 usable image .*a\.png.*b\.png: duplicate of a\.png"
    ):
        prepare_photos(src, tmp_path / "stage")


# Each CLI call costs ~10-20 s of imports on a loaded 2-core machine: two folders only (the
# empty folder and a missing one are in tests/sfm/test_photos.py at the validation layer).
@pytest.mark.parametrize(
    "fill, message",
    [
        (
            truncated_jpeg_and_a_dot,
            (
                "no usable images",
                "dot.png: too small (1x1",
                "full.jpg: unreadable",
                "notes.txt: not an image",
            ),
        ),
        (single_image, ("only 1 usable image", "only.png")),
    ],
)
def test_unusable_photo_folders_fail_cleanly_through_the_cli(tmp_path, fill, message):
    src = tmp_path / "photos"
    src.mkdir()
    fill(src)
    ws = tmp_path / "ws"
    proc = recon_cli("sfm", str(src), "-w", str(ws), check=False)
    assert_one_line_error(proc, *message)
    assert not ws.exists() or not [p for p in ws.iterdir() if p.name != ".locks"], list(
        ws.rglob("*")
    )
