"""Why an image did not register, read from the COLMAP database, and summary numbers of a
model. Users' first question after SfM is "why are only some of my photos in?"; the database
holds the answer: how many keypoints each image got, how many raw matches and how many
geometrically verified inlier matches its best partner has.
"""

from __future__ import annotations

import zlib  # noqa: F401  (before pycolmap: importing pycolmap first corrupts zlib's heap)
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

MIN_KEYPOINTS = 50  # below this an image has no usable texture for SIFT


@dataclass(frozen=True)
class ImageMatchStats:
    """Per-image evidence from the database."""

    num_keypoints: int  # SIFT keypoints extracted
    best_raw_matches: int  # most descriptor matches with any other image
    best_inliers: int  # most verified two-view inlier matches with any other image
    num_verified_pairs: int  # partners with at least `min_inliers` verified inliers


def image_match_stats(database: Path, min_inliers: int) -> dict[str, ImageMatchStats]:
    """name -> ImageMatchStats for every image in the database."""
    db = pycolmap.Database.open(database)
    try:
        images = {im.image_id: im.name for im in db.read_all_images()}
        keypoints = {i: db.num_keypoints_for_image(i) for i in images}
        raw_ids, raw_counts = db.read_num_matches()
        inlier_ids, inlier_counts = db.read_two_view_geometry_num_inliers()
    finally:
        db.close()
    best_raw = dict.fromkeys(images, 0)
    best_inl = dict.fromkeys(images, 0)
    verified = dict.fromkeys(images, 0)
    for pair_id, count in zip(raw_ids, raw_counts):
        for i in pycolmap.pair_id_to_image_pair(pair_id):
            best_raw[i] = max(best_raw[i], int(count))
    for pair_id, count in zip(inlier_ids, inlier_counts):
        for i in pycolmap.pair_id_to_image_pair(pair_id):
            best_inl[i] = max(best_inl[i], int(count))
            verified[i] += int(count >= min_inliers)
    return {
        name: ImageMatchStats(keypoints[i], best_raw[i], best_inl[i], verified[i])
        for i, name in images.items()
    }


def unregistered_reason(
    stats: ImageMatchStats | None, min_inliers: int, other_model: int | None
) -> str:
    """One line saying why an image is not in the kept model, most basic cause first."""
    if stats is None:
        return "not in the feature database (COLMAP could not read it)"
    if stats.num_keypoints < MIN_KEYPOINTS:
        return f"no features: {stats.num_keypoints} SIFT keypoints (blank, blurred or too dark?)"
    if stats.best_raw_matches < min_inliers:
        return (
            f"too few matches: best partner image has {stats.best_raw_matches} descriptor matches "
            f"({stats.num_keypoints} keypoints); little overlap with the other photos?"
        )
    if stats.num_verified_pairs == 0:
        return (
            f"no verified pair: best partner has {stats.best_raw_matches} matches but only "
            f"{stats.best_inliers} fit one camera motion (needs {min_inliers})"
        )
    if other_model is not None:
        return (
            f"registered only in a separate, smaller model (#{other_model}): "
            "too little overlap with the photos of the main model"
        )
    return (
        f"verified pairs exist ({stats.num_verified_pairs}, best {stats.best_inliers} inliers) but "
        "the mapper could not place it against the 3D points (pose estimation failed)"
    )


def model_stats(model: pycolmap.Reconstruction) -> dict:
    """Summary numbers of a reconstruction: registered images, points, errors, track length."""
    return {
        "registered_images": model.num_reg_images(),
        "points3d": model.num_points3D(),
        "observations": model.compute_num_observations(),
        "mean_reprojection_error_px": float(model.compute_mean_reprojection_error()),
        "mean_track_length": float(model.compute_mean_track_length()),
        "mean_observations_per_image": float(model.compute_mean_observations_per_reg_image()),
    }


def camera_summary(model: pycolmap.Reconstruction) -> list[dict]:
    """Every camera of a model as plain JSON: model name, size and parameters."""
    return [
        {
            "camera_id": int(cam_id),
            "model": cam.model.name,
            "width": int(cam.width),
            "height": int(cam.height),
            "params": [float(p) for p in np.asarray(cam.params)],
        }
        for cam_id, cam in sorted(model.cameras.items())
    ]


def registered_names(model: pycolmap.Reconstruction) -> set[str]:
    return {im.name for im in model.images.values() if im.has_pose}


def pair_parallax(database: Path, min_inliers: int) -> np.ndarray:
    """Degrees of parallax (K,) of each verified image pair with at least `min_inliers` inlier
    matches: the median triangulation angle of its inliers under its two-view pose, computed as
    COLMAP's mapper does for a candidate initial pair (`estimate_two_view_geometry_pose`; the
    database keeps the pair's epipolar geometry, not that angle). The mapper starts only from a
    pair above its `init_min_tri_angle`. A forward-facing capture has a few degrees on every
    pair (llff_flower: at most 3.8 over 561 pairs); an object walked around has tens (fox: 512
    of its 889 pairs above 16)."""
    db = pycolmap.Database.open(database)
    try:
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
        camera_of = {im.image_id: im.camera_id for im in db.read_all_images()}
        pair_ids, geometries = db.read_two_view_geometries()
        keypoints: dict[int, np.ndarray] = {}
        angles = []
        for pair_id, geometry in zip(pair_ids, geometries):
            if len(geometry.inlier_matches) < min_inliers:
                continue
            ids = pycolmap.pair_id_to_image_pair(pair_id)
            for i in ids:
                if i not in keypoints:
                    keypoints[i] = db.read_keypoints(i)[:, :2].astype(np.float64)
            a, b = ids
            cam_a, cam_b = cameras[camera_of[a]], cameras[camera_of[b]]
            if pycolmap.estimate_two_view_geometry_pose(
                cam_a, keypoints[a], cam_b, keypoints[b], geometry
            ):
                angles.append(np.degrees(geometry.tri_angle))
    finally:
        db.close()
    return np.asarray(angles, dtype=np.float64)
