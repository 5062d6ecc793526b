"""Pictures of one evaluated view for report.html: the photo, the render, a per-pixel error heat
map and the colourised depth, each as a full-size PNG and a small JPEG thumbnail."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from recon.io.atomic import atomic_path
from recon.io.images import to_uint8, write_png

ERROR_MAX = 0.25  # the heat map's top colour: mean absolute error over RGB of 0.25 or more
THUMB_SIDE = 200  # longer side of the thumbnails (px)
KINDS = ("gt", "render", "error", "depth")


def colourise(values: np.ndarray, lo: float, hi: float, valid: np.ndarray | None = None):
    """(H, W) values -> (H, W, 3) uint8 RGB through the turbo colour map, lo -> its first colour,
    hi -> its last; pixels outside `valid` are black."""
    t = np.clip((values - lo) / max(hi - lo, 1e-12), 0, 1)
    rgb = cv2.applyColorMap(to_uint8(t), cv2.COLORMAP_TURBO)[..., ::-1]
    if valid is not None:
        rgb = np.where(valid[..., None], rgb, 0)
    return np.ascontiguousarray(rgb, np.uint8)


def error_map(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Mean absolute error over RGB per pixel, (H, W, 3) x 2 -> (H, W) heat map, 0 -> dark
    blue, ERROR_MAX and above -> dark red (the same scale for every view and run)."""
    return colourise(np.abs(pred - gt).mean(-1), 0.0, ERROR_MAX)


def depth_map(depth: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """Expected depth (H, W) where the opacity `acc` > 0.5, as inverse depth between its 2nd
    and 98th percentiles (near = red, far = blue); black where the render is empty."""
    valid = (acc > 0.5) & (depth > 0) & np.isfinite(depth)
    if not valid.any():
        return np.zeros((*depth.shape, 3), np.uint8)
    inv = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0)
    lo, hi = np.percentile(inv[valid], [2, 98])
    return colourise(inv, lo, hi, valid)


def write_thumbnail(path: Path, image: np.ndarray, side: int = THUMB_SIDE) -> None:
    """uint8 or [0, 1] float RGB -> a JPEG whose longer side is at most `side`, atomically."""
    img = image if image.dtype == np.uint8 else to_uint8(image)
    h, w = img.shape[:2]
    scale = min(1.0, side / max(h, w))
    small = cv2.resize(
        img, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA
    )
    ok, buf = cv2.imencode(
        ".jpg", cv2.cvtColor(small, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85]
    )
    if not ok:
        raise OSError(f"JPEG encoding failed for {path}")
    with atomic_path(Path(path)) as tmp:
        buf.tofile(str(tmp))


def write_view_pictures(
    directory: Path, name: str, gt: np.ndarray, pred: np.ndarray, depth: np.ndarray, acc: np.ndarray
) -> dict[str, dict[str, str]]:
    """The four pictures of view `name` -> directory/{name}_{kind}.png and thumbs/...jpg;
    returns {kind: {"full": file name, "thumb": "thumbs/..."}} relative to `directory`."""
    pictures = {
        "gt": to_uint8(gt),
        "render": to_uint8(pred),
        "error": error_map(pred, gt),
        "depth": depth_map(depth, acc),
    }
    stem = Path(name).stem
    out = {}
    for kind, image in pictures.items():
        full, thumb = f"{stem}_{kind}.png", f"thumbs/{stem}_{kind}.jpg"
        write_png(directory / full, image)
        write_thumbnail(directory / thumb, image)
        out[kind] = {"full": full, "thumb": thumb}
    return out
