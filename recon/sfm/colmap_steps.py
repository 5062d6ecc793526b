"""The COLMAP phases one by one, over pycolmap 4.x: feature extraction, pair selection and
matching, mapping, undistortion. Each phase is split into chunks only to report progress.

`colmap_sfm.run_sfm` strings these together; nothing here knows about attempts or reports.
"""

from __future__ import annotations

import contextlib
import re
import shutil
import time
import zlib  # noqa: F401  (before pycolmap: importing pycolmap first corrupts zlib's heap)
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

Progress = Callable[[str, int, int], None]

# SIFT peak threshold COLMAP uses by default (0.02 / octave_resolution).
DEFAULT_PEAK_THRESHOLD = 0.02 / 3
# SIFT's first octave at -1 doubles the image first (4x the pyramid cost, ~2.5x the keypoints,
# and matching and mapping grow with them) to find small blobs; worth it only on small images,
# where the 0-octave keypoints are too few to pose them (Lowe 2004, Sec. 3.3).
SIFT_UPSAMPLE_BELOW = 800  # px, longer side after the max_image_size downscale
EXTRACTION_CHUNK = 8  # images per extract_features call: progress granularity vs. thread start-up
MATCHING_CHUNK = 150  # image pairs per match_image_pairs call
# The incremental mapper's global bundle adjustments (Schönberger & Frahm 2016, Sec. 4.5).
# COLMAP adjusts the whole model each time it grew by 10 % and repeats each adjustment up to
# 5 times with re-triangulation in between. Local adjustments keep each new image right in
# between and `refine_intrinsics` ends with a full adjustment, so recon adjusts globally every
# 30 % of growth. From LIGHT_GLOBAL_BA_IMAGES photos on, where these adjustments are most of
# the mapping time, every 50 %, once each time, leaving out points whose cameras are already
# well covered by others (COLMAP's `ba_global_ignore_redundant_points3D`); on a small model
# that schedule saves seconds and costs a little accuracy (bench/results/2026-11-29-sfm-speed.md).
GLOBAL_BA_GROWTH = 1.3
LIGHT_GLOBAL_BA_IMAGES = 150
LIGHT_GLOBAL_BA_GROWTH = 1.5
LIGHT_GLOBAL_BA_REFINEMENTS = 1
# The incremental mapper runs on one thread whatever `num_threads` says: with two, the
# results of its multi-threaded steps depend on timing in their last bits, and on a hard
# capture those bits decide whether an initial pair or a next image is accepted (a 12-photo
# ring registered 8 photos in most runs and 2 in others from one database). Most of its time
# is single-threaded anyway (fox: 9.5 s on one thread, 10.2 s on two; llff_flower, whose
# adjustments are denser, 18.6 s against 12.6).
INCREMENTAL_MAPPER_THREADS = 1
# Bundle adjustments stop when an iteration lowers the cost by less than this fraction (Ceres'
# own default; COLMAP sets 0, so its adjustments run to their iteration cap). The last digits
# it leaves move no pose measurably (fox: median rotation error 0.0187 against 0.0189 deg) and
# the final adjustment of 300 photos takes 6 s instead of 27.
BA_FUNCTION_TOLERANCE = 1e-6


@dataclass(frozen=True)
class AttemptOptions:
    """Everything one SfM attempt varies: features, matching, and mapper thresholds."""

    name: str  # short label for the report
    max_image_size: int  # longer side the SIFT extractor downscales to (keypoints stay full-res)
    max_num_features: int  # SIFT keypoints kept per image
    peak_threshold: float  # SIFT DoG peak threshold; lower finds more keypoints in low contrast
    always_upsample: bool  # SIFT first octave -1 on every image, not only small ones
    matcher: str  # "exhaustive" | "retrieval" (VLAD nearest) | "sequential" (windowed + loops)
    guided_matching: bool  # re-match with the estimated epipolar geometry (more inliers, slower)
    min_num_inliers: int  # two-view geometry: inliers for a pair to count as verified
    min_num_matches: int  # mapper: verified inliers for a pair to be used at all
    init_min_num_inliers: int  # mapper: inliers the initial pair needs
    abs_pose_min_num_inliers: int  # mapper: 2D-3D inliers to register a new image
    abs_pose_min_inlier_ratio: float  # mapper: inlier ratio to register a new image
    init_min_tri_angle: float = 16.0  # mapper: degrees of parallax the initial pair needs


@contextlib.contextmanager
def glog_level(verbose: bool):
    """Silence COLMAP's glog INFO/WARNING lines unless verbose; restore the level after."""
    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if verbose else 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = previous


def natural_key(name: str) -> list:
    """Sort key in which "img2" < "img10": capture order for sequential matching."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def chunks(items: list, size: int) -> list[list]:
    return [items[i : i + size] for i in range(0, len(items), size)]


def first_octave(longer_side: int, options: AttemptOptions) -> int:
    """-1 (upsample 2x) for images whose SIFT size is under SIFT_UPSAMPLE_BELOW, else 0."""
    sift_size = min(longer_side, options.max_image_size)
    return -1 if options.always_upsample or sift_size < SIFT_UPSAMPLE_BELOW else 0


def extract_features(
    database: Path,
    image_dir: Path,
    groups: list[tuple[list[str], int]],
    options: AttemptOptions,
    camera_model: str,
    num_threads: int,
    progress: Progress,
) -> None:
    """SIFT keypoints and descriptors for every image into `database`.

    `groups` lists (names, longer side in px) of the images that share one camera (one group
    per image for per-image cameras). The first chunk of a group creates its camera; later
    chunks reuse it through `existing_camera_id`, so the camera stays shared across calls.
    """
    total, done = sum(len(names) for names, _ in groups), 0
    progress("features", 0, total)
    pycolmap.Database.open(database).close()  # import_images needs the file
    for group, longer_side in groups:
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.max_image_size = options.max_image_size
        extraction.num_threads = num_threads
        extraction.sift.max_num_features = options.max_num_features
        extraction.sift.peak_threshold = options.peak_threshold
        extraction.sift.first_octave = first_octave(longer_side, options)
        camera_id = -1
        for names in chunks(group, EXTRACTION_CHUNK):
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model = camera_model
            reader.existing_camera_id = camera_id
            # Image ids in name order. COLMAP's extractor writes an image's row when a worker
            # finishes it, so with several threads the ids (and with them the pair ids, the
            # orientation of every match and the mapper's tie-breaks) depended on timing;
            # images imported first keep their ids and the extractor fills in their features.
            pycolmap.import_images(
                database,
                image_dir,
                camera_mode=pycolmap.CameraMode.SINGLE,
                image_names=names,
                options=reader,
            )
            pycolmap.extract_features(
                database,
                image_dir,
                image_names=names,
                camera_mode=pycolmap.CameraMode.SINGLE,
                reader_options=reader,
                extraction_options=extraction,
                device=pycolmap.Device.cpu,
            )
            if camera_id == -1:
                camera_id = camera_of_image(database, names[0])
            done += len(names)
            progress("features", done, total)


def camera_of_image(database: Path, name: str) -> int:
    db = pycolmap.Database.open(database)
    try:
        return db.read_image_with_name(name).camera_id
    finally:
        db.close()


def exhaustive_pairs(names: list[str]) -> list[tuple[str, str]]:
    """All N (N - 1) / 2 pairs."""
    return [(a, b) for i, a in enumerate(names) for b in names[i + 1 :]]


def sequential_pairs(
    names: list[str], overlap: int = 10, num_keyframes: int = 40
) -> list[tuple[str, str]]:
    """Pairs for an ordered capture (video, walk-around): each image with its `overlap` next
    ones, with the ones 2^k further (COLMAP's quadratic overlap), plus all pairs among
    ~`num_keyframes` evenly spaced keyframes. The keyframe pairs close loops (the end of an
    orbit meets its start) without the vocabulary tree COLMAP's loop detection needs.
    """
    order = sorted(names, key=natural_key)
    n = len(order)
    pairs: set[tuple[int, int]] = set()
    for i in range(n):
        steps = set(range(1, overlap + 1)) | {2**k for k in range(overlap)}
        pairs.update((i, i + s) for s in steps if i + s < n)
    stride = max(1, n // num_keyframes)
    keyframes = list(range(0, n, stride))
    pairs.update((a, b) for k, a in enumerate(keyframes) for b in keyframes[k + 1 :])
    return [(order[a], order[b]) for a, b in sorted(pairs)]


def read_descriptors(database: Path, names: list[str]) -> list[np.ndarray]:
    """(N_i, 128) uint8 SIFT descriptors of each named image, in the order of `names`."""
    db = pycolmap.Database.open(database)
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        return [np.asarray(db.read_descriptors(ids[n]).data) for n in names]
    finally:
        db.close()


def two_view_options(options: AttemptOptions, seed: int) -> pycolmap.TwoViewGeometryOptions:
    verification = pycolmap.TwoViewGeometryOptions()
    verification.min_num_inliers = options.min_num_inliers
    verification.ransac.random_seed = seed
    return verification


def match_pairs(
    database: Path,
    work_dir: Path,
    pairs: list[tuple[str, str]],
    options: AttemptOptions,
    seed: int,
    num_threads: int,
    progress: Progress,
) -> None:
    """Match descriptors and verify two-view geometry for `pairs`, `MATCHING_CHUNK` at a time.

    Every chunk is one `match_image_pairs` call over a pairs file, which gives progress and
    lets exhaustive and sequential matching share one code path (pairs already in the
    database are skipped by COLMAP).
    """
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    matching.guided_matching = options.guided_matching
    verification = two_view_options(options, seed)
    pairs_file = work_dir / "pairs.txt"
    progress("matching", 0, len(pairs))
    done = 0
    for chunk in chunks(pairs, MATCHING_CHUNK):
        pairs_file.write_text("".join(f"{a} {b}\n" for a, b in chunk))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(pairs_file)
        pycolmap.match_image_pairs(
            database,
            matching_options=matching,
            pairing_options=pairing,
            verification_options=verification,
            device=pycolmap.Device.cpu,
        )
        done += len(chunk)
        progress("matching", done, len(pairs))
    pairs_file.unlink()


def incremental_options(
    options: AttemptOptions, names: list[str], seed: int, num_threads: int
) -> pycolmap.IncrementalPipelineOptions:
    pipeline = pycolmap.IncrementalPipelineOptions()
    pipeline.num_threads = num_threads
    pipeline.random_seed = seed
    pipeline.image_names = names
    pipeline.min_num_matches = options.min_num_matches
    pipeline.mapper.init_min_num_inliers = options.init_min_num_inliers
    pipeline.mapper.abs_pose_min_num_inliers = options.abs_pose_min_num_inliers
    pipeline.mapper.abs_pose_min_inlier_ratio = options.abs_pose_min_inlier_ratio
    pipeline.mapper.init_min_tri_angle = options.init_min_tri_angle
    pipeline.ba_global_function_tolerance = BA_FUNCTION_TOLERANCE
    pipeline.ba_local_function_tolerance = BA_FUNCTION_TOLERANCE
    light = len(names) >= LIGHT_GLOBAL_BA_IMAGES
    growth = LIGHT_GLOBAL_BA_GROWTH if light else GLOBAL_BA_GROWTH
    pipeline.ba_global_frames_ratio = pipeline.ba_global_points_ratio = growth
    if light:
        pipeline.ba_global_max_refinements = LIGHT_GLOBAL_BA_REFINEMENTS
        pipeline.mapper.ba_global_ignore_redundant_points3D = True
    # Small captures are still worth a model: COLMAP's default refuses models under 10 images.
    pipeline.min_model_size = min(10, max(2, len(names) // 2))
    return pipeline


def map_images(
    database: Path,
    image_dir: Path,
    output_dir: Path,
    names: list[str],
    mapper: str,
    options: AttemptOptions,
    seed: int,
    num_threads: int,
    progress: Progress,
) -> dict[int, pycolmap.Reconstruction]:
    """Incremental (COLMAP) or global (GLOMAP) mapping with bundle adjustment -> models."""
    output_dir.mkdir(parents=True, exist_ok=True)
    total = len(names)
    progress("mapping", 0, total)
    if mapper == "global":
        pipeline = pycolmap.GlobalPipelineOptions()
        pipeline.num_threads = num_threads
        pipeline.random_seed = seed
        pipeline.image_names = names
        pipeline.min_num_matches = options.min_num_matches
        models = pycolmap.global_mapping(database, image_dir, output_dir, pipeline)
    else:
        registered = [0]

        def next_image() -> None:  # called once per newly registered image
            registered[0] += 1
            progress("mapping", min(registered[0] + 1, total), total)

        pipeline = incremental_options(options, names, seed, INCREMENTAL_MAPPER_THREADS)
        models = pycolmap.incremental_mapping(
            database, image_dir, output_dir, pipeline, next_image_callback=next_image
        )
    progress("mapping", total, total)
    return dict(models)


# A camera's principal point is refined only when at least this many registered images share
# it: one or two views cannot tell it from a rotation of the camera.
PRINCIPAL_POINT_MIN_IMAGES = 8


def refine_intrinsics(model: pycolmap.Reconstruction, principal_point: bool) -> dict:
    """A last global bundle adjustment of the kept model in place, refining focal length and
    distortion and, with `principal_point`, the principal point of cameras shared by at least
    PRINCIPAL_POINT_MIN_IMAGES images. COLMAP's mapper holds the principal point at the image
    centre while it grows the model (early, few-view models cannot constrain it); the final
    adjustment over all images can, as instant-ngp's colmap2nerf and nerfstudio do after
    mapping. Returns the mean reprojection error (px) before and after, and what was refined.
    """
    images_per_camera: dict[int, int] = {}
    for image in model.images.values():
        if image.has_pose:
            images_per_camera[image.camera_id] = images_per_camera.get(image.camera_id, 0) + 1
    refine_pp = principal_point and min(images_per_camera.values(), default=0) >= (
        PRINCIPAL_POINT_MIN_IMAGES
    )
    before = float(model.compute_mean_reprojection_error())
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_principal_point = refine_pp
    options.ceres.solver_options.function_tolerance = BA_FUNCTION_TOLERANCE
    options.print_summary = (
        False  # COLMAP prints its report whatever glog's level (the report has the errors)
    )
    pycolmap.bundle_adjustment(model, options)
    model.update_point_3d_errors()
    return {
        "principal_point_refined": refine_pp,
        "reprojection_error_before_px": round(before, 4),
        "reprojection_error_after_px": round(float(model.compute_mean_reprojection_error()), 4),
    }


def undistort(
    model: pycolmap.Reconstruction, image_dir: Path, work_dir: Path, num_threads: int
) -> Path:
    """Undistort the registered images to PINHOLE cameras -> work_dir/undistorted
    (images/ and sparse/; COLMAP also writes stereo/ configs for its dense pipeline)."""
    model_dir = work_dir / "sparse_best"
    model_dir.mkdir(parents=True, exist_ok=True)
    model.write(model_dir)
    output = work_dir / "undistorted"
    shutil.rmtree(output, ignore_errors=True)  # no stale images from an earlier run
    pycolmap.undistort_images(
        output, model_dir, image_dir, output_type="COLMAP", num_threads=num_threads
    )
    return output


class PhaseTimer:
    """Wall and process-CPU seconds per phase; CPU time (all threads) stays meaningful when
    other jobs share the cores and stretch wall time."""

    def __init__(self) -> None:
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}

    @contextlib.contextmanager
    def __call__(self, phase: str):
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.wall[phase] = self.wall.get(phase, 0.0) + time.perf_counter() - wall
            self.cpu[phase] = self.cpu.get(phase, 0.0) + time.process_time() - cpu

    def as_dict(self) -> dict:
        return {
            "wall_s": {k: round(v, 2) for k, v in self.wall.items()},
            "cpu_s": {k: round(v, 2) for k, v in self.cpu.items()},
        }


@dataclass
class Attempt:
    """One attempt's outcome."""

    options: AttemptOptions
    directory: Path
    models: dict[int, pycolmap.Reconstruction]
    timer: PhaseTimer
    retried: list[str] = field(default_factory=list)  # photos a retry re-extracted / re-matched
    pairs_matched: int = 0  # image pairs sent to the matcher (already matched pairs are skipped)
    max_pair_parallax: float | None = None  # degrees, the first attempt's (`pair_parallax`)

    @property
    def best(self) -> pycolmap.Reconstruction | None:
        """The largest model (most registered images, then most points)."""
        if not self.models:
            return None
        return max(self.models.values(), key=lambda m: (m.num_reg_images(), m.num_points3D()))

    @property
    def registered(self) -> int:
        return self.best.num_reg_images() if self.models else 0

    @property
    def database(self) -> Path:
        return self.directory / "database.db"
