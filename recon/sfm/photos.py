"""Finding, validating and staging the photos of a capture before SfM.

A photo folder from a user holds more than clean JPEGs: sidecar files, truncated uploads,
thumbnails, copies of the same shot, phone pictures stored sideways with an EXIF rotation
flag, 16-bit PNGs. Each file is sniffed by content, fully decoded, and either accepted or
listed with the reason it was skipped. Accepted photos are staged into one flat folder that
COLMAP reads: a symlink when the file can be used as is, an 8-bit upright copy when COLMAP
would misread it (EXIF rotation, 16-bit samples, a format or file name it does not know).
"""

from __future__ import annotations

import hashlib
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps

# Formats COLMAP reads directly; anything else Pillow decodes is converted to PNG.
NATIVE_FORMATS = {"JPEG": ".jpg", "PNG": ".png", "TIFF": ".tif"}
NATIVE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff"}
EXIF_ORIENTATION_TAG = 0x0112


class PhotoError(ValueError):
    """Bad photo input (missing/empty folder, no usable images); the message is one line."""


@dataclass(frozen=True)
class Photo:
    """One usable photo: where it came from and how it was staged for COLMAP."""

    source: Path  # the user's file
    name: str  # file name inside the staging folder (what COLMAP and the outputs call it)
    width: int  # upright size in pixels
    height: int
    mode: str  # Pillow mode of the source (RGB, L, I;16, RGBA ...)
    converted: str  # "" if symlinked as is, else why an 8-bit upright copy was written
    sha1: str  # content hash of the source file, used to spot exact duplicates


@dataclass(frozen=True)
class PhotoSet:
    """The outcome of `prepare_photos`: usable photos and every file that was left out."""

    photos: tuple[Photo, ...]  # usable photos, sorted by source file name
    skipped: tuple[tuple[str, str], ...]  # (source file name, reason) for each rejected file
    staging_dir: Path  # flat folder holding one entry per usable photo

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.photos]


def png_bit_depth(path: Path) -> int:
    """Bit depth per sample from a PNG's IHDR chunk (byte 24), 8 for anything that is not a PNG.

    Pillow silently opens 16-bit RGB PNGs as 8-bit RGB, so the file itself must be asked.
    """
    with open(path, "rb") as f:
        head = f.read(25)
    if len(head) == 25 and head.startswith(b"\x89PNG\r\n\x1a\n") and head[12:16] == b"IHDR":
        return head[24]
    return 8


def bits_per_sample(path: Path) -> int:
    """Largest bits per sample of a PNG or TIFF file (TIFF tag 258), 8 for other formats."""
    with Image.open(path) as image:
        if image.format == "TIFF":
            bits = image.tag_v2.get(258, 8)
            return max(bits) if isinstance(bits, tuple) else int(bits)
    return png_bit_depth(path)


def list_photo_files(folder: Path) -> list[Path]:
    """Regular files directly in `folder` (sorted, hidden files ignored); raises on a bad folder."""
    folder = Path(folder)
    if not folder.exists():
        raise PhotoError(f"image folder {folder} does not exist")
    if not folder.is_dir():
        raise PhotoError(f"{folder} is not a folder")
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    if not files:
        raise PhotoError(f"image folder {folder} is empty")
    return files


def file_sha1(path: Path) -> str:
    h = hashlib.sha1()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def exif_orientation(image: Image.Image) -> int:
    """EXIF orientation flag 1..8 (1 = upright, also when absent or invalid)."""
    try:
        value = int(image.getexif().get(EXIF_ORIENTATION_TAG, 1))
    except (TypeError, ValueError):
        return 1
    return value if 1 <= value <= 8 else 1


def decode_photo(path: Path) -> tuple[Image.Image, str, bool]:
    """Decode a whole file -> (upright image, format, was rotated). Raises ValueError(reason).

    `Image.load()` decodes every pixel, so truncated or corrupt files fail here rather than
    in the middle of feature extraction.
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            image = Image.open(path)
            image.load()
    except Exception as exc:  # Pillow raises many exception types for bad files
        kind = "not an image" if isinstance(exc, Image.UnidentifiedImageError) else "unreadable"
        detail = (str(exc).splitlines() or [""])[0][:80]
        raise ValueError(f"{kind} ({type(exc).__name__}: {detail})") from exc
    fmt = image.format or "unknown"
    rotated = exif_orientation(image) != 1
    if rotated:
        image = ImageOps.exif_transpose(image)
    return image, fmt, rotated


def to_8bit(image: Image.Image) -> Image.Image:
    """Image in L, RGB or RGBA with 8-bit samples; 16-bit and float data are rescaled."""
    if image.mode in ("L", "RGB", "RGBA"):
        return image
    if image.mode in ("I;16", "I;16B", "I;16L", "I", "F"):
        values = np.asarray(image, dtype=np.float64)
        # 16-bit PNG/TIFF use the full 0..65535 range; float TIFFs are taken as 0..1.
        scale = 1.0 / 257.0 if image.mode != "F" else 255.0
        return Image.fromarray(np.clip(np.rint(values * scale), 0, 255).astype(np.uint8), "L")
    if image.mode in ("LA", "PA"):
        return image.convert("RGBA")
    return image.convert("RGB")


def conversion_reason(image: Image.Image, fmt: str, path: Path, rotated: bool) -> str:
    """Why the photo cannot be handed to COLMAP as is ("" when a symlink will do)."""
    if rotated:
        return "EXIF rotation applied"
    if bits_per_sample(path) > 8:
        return f"{bits_per_sample(path)}-bit {fmt} converted to 8 bit"
    if image.mode not in ("L", "RGB", "RGBA"):
        return f"{image.mode} image converted to 8-bit L/RGB"
    if fmt not in NATIVE_FORMATS:
        return f"{fmt} converted to PNG"
    if path.suffix.lower() not in NATIVE_SUFFIXES:
        return f"{fmt} file without a {fmt} extension"
    return ""


def staged_name(path: Path, fmt: str, reason: str) -> str:
    """Staging name: the source name with whitespace replaced by "_" (COLMAP's pair lists
    are space-separated), plus a real image extension when the photo was converted."""
    name = re.sub(r"\s", "_", path.name)
    if not reason or path.suffix.lower() in NATIVE_SUFFIXES and fmt in NATIVE_FORMATS:
        return name
    return name + NATIVE_FORMATS.get(fmt, ".png")


def inspect_photo(path: Path, min_side: int) -> Photo:
    """Validate one file and describe how to stage it. Raises ValueError(reason) if unusable."""
    image, fmt, rotated = decode_photo(path)
    width, height = image.size
    if min(width, height) < min_side:
        raise ValueError(f"too small ({width}x{height}, shorter side under {min_side} px)")
    reason = conversion_reason(image, fmt, path, rotated)
    name = staged_name(path, fmt, reason)
    return Photo(path, name, width, height, image.mode, reason, file_sha1(path))


def stage_photo(photo: Photo, staging_dir: Path) -> None:
    """Put `photo` into the staging folder: a symlink, or an 8-bit upright copy."""
    target = staging_dir / photo.name
    if target.is_symlink() or target.exists():
        target.unlink()
    if not photo.converted:
        os.symlink(photo.source.resolve(), target)
        return
    image, _, _ = decode_photo(photo.source)
    image = to_8bit(image)
    if target.suffix.lower() in (".jpg", ".jpeg"):
        exif = image.getexif()
        exif.pop(EXIF_ORIENTATION_TAG, None)  # pixels are upright now; keep focal length tags
        image.convert("RGB").save(target, quality=95, exif=exif.tobytes())
    else:
        image.save(target)


def skipped_summary(skipped: list[tuple[str, str]], shown: int = 3) -> str:
    """'a.jpg: unreadable (...); b.png: duplicate of c.png; +2 more' - which files and why, on
    one line, so an error about too few photos says what happened to the others."""
    parts = [f"{name}: {reason}" for name, reason in skipped[:shown]]
    if len(skipped) > shown:
        parts.append(f"+{len(skipped) - shown} more")
    return "; ".join(parts)


def prepare_photos(image_dir: Path, staging_dir: Path, min_side: int = 64) -> PhotoSet:
    """Validate every file of `image_dir` and stage the usable photos into `staging_dir`.

    Skipped (with a reason): files that are not images, corrupt or truncated images, images
    whose shorter side is under `min_side` pixels, and exact duplicates of an earlier file
    (identical photos give a zero-baseline pair that SfM cannot triangulate from).
    Raises PhotoError for a missing or empty folder and for fewer than 2 usable photos.
    """
    files = list_photo_files(Path(image_dir))
    photos: list[Photo] = []
    skipped: list[tuple[str, str]] = []
    first_by_hash: dict[str, str] = {}
    for path in files:
        try:
            photo = inspect_photo(path, min_side)
        except ValueError as exc:
            skipped.append((path.name, str(exc)))
            continue
        if photo.sha1 in first_by_hash:
            skipped.append((path.name, f"duplicate of {first_by_hash[photo.sha1]}"))
            continue
        if any(p.name == photo.name for p in photos):
            skipped.append((path.name, f"staged name {photo.name} is taken by another photo"))
            continue
        first_by_hash[photo.sha1] = path.name
        photos.append(photo)
    if not photos:
        raise PhotoError(
            f"no usable images in {image_dir} ({len(files)} files, {len(skipped)} skipped: "
            f"{skipped_summary(skipped)})"
        )
    if len(photos) < 2:
        why = f"; skipped: {skipped_summary(skipped)}" if skipped else ""
        raise PhotoError(
            f"only 1 usable image in {image_dir} ({photos[0].source.name}); SfM needs at least 2{why}"
        )
    staging_dir = Path(staging_dir)
    staging_dir.mkdir(parents=True, exist_ok=True)
    for photo in photos:
        stage_photo(photo, staging_dir)
    return PhotoSet(tuple(photos), tuple(skipped), staging_dir)
