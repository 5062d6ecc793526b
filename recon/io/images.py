"""Image files <-> float arrays in [0, 1]. cv2 does the decoding (it handles 8/16-bit,
grey, alpha); arrays are RGB(A) float32, (H, W, C)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from recon.io.atomic import atomic_path


class ImageReadError(ValueError):
    pass


def read_image(path: Path) -> np.ndarray:
    """Decode an image to float32 RGB or RGBA in [0, 1], (H, W, 3|4). Raises ImageReadError."""
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH) if data.size else None
    if img is None:
        raise ImageReadError(f"cannot decode image {path}")
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    img = img.astype(np.float32) / scale
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    elif img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    elif img.shape[2] == 2:  # grey + alpha
        img = np.concatenate([np.repeat(img[..., :1], 3, axis=-1), img[..., 1:]], axis=-1)
    return img


def composite(rgba: np.ndarray, background: np.ndarray) -> np.ndarray:
    """C = alpha * rgb + (1 - alpha) * background for RGBA (H, W, 4); RGB passes through."""
    if rgba.shape[-1] == 3:
        return rgba
    a = rgba[..., 3:4]
    return rgba[..., :3] * a + (1.0 - a) * np.asarray(background, np.float32)


def resize_area(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-averaged resampling (box filter), the right filter for downscaling."""
    if img.shape[1] == width and img.shape[0] == height:
        return img
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)


def to_uint8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_png(path: Path, rgb: np.ndarray, compression: int | None = None) -> None:
    """Write float RGB (H, W, 3) or RGBA (H, W, 4) in [0, 1] (or uint8) as an 8-bit PNG,
    atomically; `compression` 0-9 (None: OpenCV's default)."""
    params = [] if compression is None else [cv2.IMWRITE_PNG_COMPRESSION, compression]
    _write_encoded(Path(path), ".png", rgb, params)


def write_jpeg(path: Path, rgb: np.ndarray, quality: int = 95) -> None:
    """Write float RGB (H, W, 3) in [0, 1] (or uint8) as an 8-bit JPEG, atomically."""
    _write_encoded(Path(path), ".jpg", rgb, [cv2.IMWRITE_JPEG_QUALITY, quality])


def _write_encoded(path: Path, ext: str, rgb: np.ndarray, params: list[int]) -> None:
    img = rgb if rgb.dtype == np.uint8 else to_uint8(rgb)
    bgr = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA if img.shape[-1] == 4 else cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(ext, bgr, params)
    if not ok:
        raise OSError(f"{ext[1:].upper()} encoding failed for {path}")
    with atomic_path(path) as tmp:
        buf.tofile(str(tmp))
