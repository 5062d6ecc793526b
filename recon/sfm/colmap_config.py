"""The options of the COLMAP engine (`colmap_sfm.run_sfm`), one `recon sfm` flag each. No
pycolmap import here: the command line reads these without loading COLMAP."""

from __future__ import annotations

from dataclasses import dataclass

from recon.options import opt


@dataclass(frozen=True)
class SfmConfig:
    """Options of `run_sfm` (one CLI flag each; the comment after a field is its help).

    SIFT keypoints found on the downscaled image are rescaled to full resolution. From 800 px
    SIFT skips its 2x-upsampled first octave (4x cheaper); 1024 px keeps ~1,400 keypoints on a
    phone photo, enough for poses well inside what training at a quarter of the photo's size
    can tell apart (bench/results/2026-11-29-sfm-speed.md). Matching cost grows with the
    keypoints squared per pair and with the number of pairs, which `retrieval` keeps at ~k per
    photo instead of all of them.

    The camera model is OPENCV (two focal lengths, principal point, k1, k2, p1, p2; what
    instant-ngp's colmap2nerf and nerfstudio use for photos) and a last bundle adjustment refines
    the principal point. On fox (a phone's lens: k2 matters, the principal point is 16 px off
    the centre) SIMPLE_RADIAL with the centred principal point left every camera 0.12 deg off
    the reference poses (0.6 deg common rotation; 0.7 px at the quarter size 3dgs trains at),
    OPENCV with the refined point 0.018 deg, and 3dgs trained on its poses scores higher
    (bench/results/sfm_camera_model.md).
    """

    max_image_size: int = opt(1024, "SIFT runs on photos downscaled to this longer side (px)")
    max_num_features: int = opt(4096, "SIFT keypoints kept per image")
    matcher: str = opt(
        "auto",
        "photos: feature matcher (auto: exhaustive up to 40 photos, else retrieval; sequential"
        " for video frames)",
        choices=("auto", "exhaustive", "retrieval", "sequential"),
    )
    retrieval_neighbors: int = opt(
        20, "retrieval matcher: each photo is matched with this many most similar photos"
    )
    mapper: str = opt(
        "incremental",
        "photos: incremental (COLMAP) or global (GLOMAP) mapper",
        choices=("incremental", "global"),
    )
    camera_model: str = opt(
        "OPENCV", "COLMAP camera model: OPENCV (fx, fy, cx, cy, k1, k2, p1, p2), SIMPLE_RADIAL..."
    )
    refine_principal_point: bool = opt(
        True, "a last bundle adjustment also refines the principal point (cameras of >= 8 images)"
    )
    single_camera: bool = opt(True, "one camera shared by all photos of one size (one device)")
    try_harder: bool = opt(True, "retry with more features / other matcher if photos stay out")
    min_registered: float = opt(
        0.8,
        "warn and exit with code 3 when fewer than this share of the usable photos register",
    )
    min_image_side: int = opt(64, "photos with a shorter side below this (px) are skipped")
    seed: int = opt(
        0, "RANSAC, retrieval and mapper seed (the same photos and seed give the same model)"
    )
    num_threads: int = opt(
        -1,
        "COLMAP threads for features, matching and the last adjustment (-1: all cores; the "
        "incremental mapper uses one)",
    )
    verbose: bool = opt(False, "show COLMAP's own log lines")
