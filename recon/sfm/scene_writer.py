"""Posed images -> the workspace's scene: undistorted, downscaled images, a PINHOLE COLMAP
model, `cameras.json` (normalized cameras, normalization, split, box) and `points.ply`.

Everything is built in temporary folders and swapped in at the end, so a failure leaves the
previous `images/` and `sfm/` as they were.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from recon.io.colmap_binary import write_colmap_binary
from recon.io.images import composite, read_image, resize_area, write_png
from recon.io.ply import write_points_ply
from recon.options import opt
from recon.sfm.normalize import normalize_scene
from recon.sfm.sources import PosedImages, SourceError
from recon.workspace import Workspace

BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


@dataclass(frozen=True)
class SceneConfig:
    downscale: int = opt(
        1, "integer factor; images are area-resampled and intrinsics scaled exactly"
    )
    background: str = opt(
        "auto",
        "colour that transparent pixels are composited on (auto: white)",
        choices=("auto", "white", "black"),
    )
    scene: str = opt(
        "auto",
        "bounded object (box) or unbounded capture (contraction); auto: bounded "
        "when the images have alpha",
        choices=("auto", "bounded", "unbounded"),
    )
    holdout_every: int = opt(
        8, "every N-th image is a test view unless the dataset defines a split"
    )


def undistort(img: np.ndarray, K: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undistort once (OpenCV model) to a pinhole with only valid pixels (alpha=0)."""
    h, w = img.shape[:2]
    newK, _ = cv2.getOptimalNewCameraMatrix(K, dist, (w, h), 0.0, (w, h))
    # cv2 uses pixel centres at integers; shift our +0.5 convention in and out.
    shift = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1]])
    K_cv, newK_cv = shift @ K, newK
    m1, m2 = cv2.initUndistortRectifyMap(K_cv, dist, None, newK_cv, (w, h), cv2.CV_32FC1)
    out = cv2.remap(img, m1, m2, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out, np.linalg.inv(shift) @ newK_cv


def prepare_image(
    frame, cfg: SceneConfig, background
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Load, composite, undistort and downscale one image -> (image, K, mask of alpha > 0 at the
    output size, or None without alpha; the mask is not undistorted: it only bounds the box).
    The image is RGB, or with alpha RGBA whose colour is already composited on `background`
    (what every reader of the RGB sees) and whose alpha went through the same undistortion
    and resampling (what a model may train against other backgrounds with)."""
    try:
        img = read_image(frame.path)
    except ValueError as e:
        raise SourceError(str(e)) from e
    alpha = img[..., 3] if img.shape[-1] == 4 else None
    K = frame.K.copy()
    if alpha is not None:
        img = np.concatenate([composite(img, background), alpha[..., None]], axis=-1)
    if frame.dist is not None:
        img, K = undistort(img, K, frame.dist)
    if cfg.downscale > 1:
        h, w = img.shape[:2]
        nw, nh = w // cfg.downscale, h // cfg.downscale
        img = resize_area(img, nw, nh)
        K[0, :] *= nw / w
        K[1, :] *= nh / h
    mask = resize_area(alpha, img.shape[1], img.shape[0]) > 0 if alpha is not None else None
    return img, K, mask


def prepare_depth(frame, width: int, height: int) -> np.ndarray | None:
    """The frame's ground-truth z-depth map at the output size (nearest), or None."""
    if frame.depth_path is None:
        return None
    from recon.io.exr import read_depth_exr

    depth = read_depth_exr(frame.depth_path)
    return cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)


def write_scene(
    posed: PosedImages,
    cfg: SceneConfig,
    images_out: Path,
    sfm_out: Path,
    images_rel: str,
    progress=None,
) -> dict:
    """Write images into `images_out` and the sfm files into `sfm_out` (both fresh folders).
    `images_rel` is how cameras.json names the final images folder. Returns a summary."""
    first = read_image(posed.frames[0].path)
    has_alpha = first.shape[-1] == 4
    bg_name = cfg.background if cfg.background != "auto" else "white"
    background = np.array(BACKGROUNDS[bg_name], dtype=np.float32)
    # one folder per split when names repeat across splits (Blender: train/r_0 and test/r_0)
    per_split = len({f.name for f in posed.frames}) < len(posed.frames)
    records, Ks, sizes, masks, depths = [], [], [], [], []
    for i, frame in enumerate(posed.frames):
        img, K, mask = prepare_image(frame, cfg, background)
        masks.append(mask)
        depths.append(prepare_depth(frame, img.shape[1], img.shape[0]))
        rel = f"{frame.split}/{frame.name}.png" if per_split else f"{frame.name}.png"
        write_png(images_out / rel, img)
        records.append((frame, rel, img.shape[1], img.shape[0]))
        Ks.append(K)
        sizes.append((img.shape[1], img.shape[0]))
        if progress:
            progress("images", i + 1, len(posed.frames))
    Ks, sizes = np.stack(Ks), np.array(sizes, dtype=np.float64)
    world_from_cam = np.stack([f.world_from_cam for f in posed.frames])
    sim, aabb = normalize_scene(
        world_from_cam,
        Ks,
        sizes,
        posed.points,
        depths=depths,
        masks=masks if all(m is not None for m in masks) else None,
    )
    scene_from_cam = sim.world_from_cam_to_scene(world_from_cam)
    bounded = has_alpha if cfg.scene == "auto" else cfg.scene == "bounded"
    frames_json = []
    for (frame, rel, w, h), K, s_from_c in zip(records, Ks, scene_from_cam):
        frames_json.append(
            {
                "name": frame.name,
                "split": frame.split,
                "image": f"{images_rel}/{rel}",
                "width": int(w),
                "height": int(h),
                "fx": float(K[0, 0]),
                "fy": float(K[1, 1]),
                "cx": float(K[0, 2]),
                "cy": float(K[1, 2]),
                "cam_from_world": np.linalg.inv(s_from_c).tolist(),
                **({"depth_gt": str(frame.depth_path)} if frame.depth_path else {}),
            }
        )
    cameras = {
        "convention": "OpenCV camera frame; cam_from_world maps the normalized scene frame to the camera",
        "scene_from_world": sim.to_json(),
        "aabb": aabb.tolist(),
        "unbounded": not bounded,
        "background": background.tolist(),
        "near": 0.02,
        "far": 4.0 if bounded else 1000.0,
        "config": asdict(cfg),
        "source": posed.source,
        "gt_mesh": str(posed.gt_mesh) if posed.gt_mesh else None,
        "frames": frames_json,
    }
    sfm_out.mkdir(parents=True, exist_ok=True)
    (sfm_out / Workspace.SFM_CAMERAS).write_text(json.dumps(cameras, indent=1) + "\n")
    write_colmap_model(sfm_out / Workspace.SFM_SPARSE, records, Ks, world_from_cam, posed)
    if posed.points is not None and len(posed.points):
        write_points_ply(sfm_out / Workspace.SFM_POINTS, posed.points, posed.point_colors)
    splits = {}
    for f in posed.frames:
        splits[f.split] = splits.get(f.split, 0) + 1
    return {
        "images": len(posed.frames),
        "splits": splits,
        "bounded": bounded,
        "scale": sim.scale,
        "points": 0 if posed.points is None else len(posed.points),
    }


def write_colmap_model(out: Path, records, Ks, world_from_cam, posed: PosedImages) -> None:
    """PINHOLE COLMAP binary model in the ORIGINAL world frame (one camera per distinct K/size)."""
    cam_ids: dict[tuple, int] = {}
    cameras, images = [], []
    for i, ((frame, rel, w, h), K) in enumerate(zip(records, Ks)):
        key = (w, h) + tuple(np.round(K[[0, 1, 0, 1], [0, 1, 2, 2]], 6))
        if key not in cam_ids:
            cam_ids[key] = len(cam_ids) + 1
            cameras.append((cam_ids[key], int(w), int(h), K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        images.append((i + 1, rel, cam_ids[key], np.linalg.inv(world_from_cam[i])))
    write_colmap_binary(out, cameras, images, posed.points, posed.point_colors)
