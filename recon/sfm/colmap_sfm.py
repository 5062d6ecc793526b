"""Structure from motion over pycolmap: photos in, a registered and undistorted (PINHOLE)
reconstruction plus a report out.

Phases: photo validation and staging (`photos.py`), SIFT extraction, pair matching with
two-view verification, incremental (or global) mapping with bundle adjustment, keeping the
largest model, a last bundle adjustment that refines the intrinsics (principal point included),
undistortion. When photos stay unregistered the engine tries harder on its own
(more features and relaxed thresholds, then another matcher with guided matching) and keeps
the best attempt; the report says which images are still out and why.
"""

from __future__ import annotations

import shutil
import time
import zlib  # noqa: F401  (before pycolmap: importing pycolmap first corrupts zlib's heap)
from dataclasses import dataclass, replace
from pathlib import Path

import pycolmap

from recon.sfm import colmap_diagnose as diagnose
from recon.sfm import colmap_retry
from recon.sfm import colmap_steps as steps
from recon.sfm.colmap_config import SfmConfig
from recon.sfm.colmap_report import build_report
from recon.sfm.colmap_steps import Attempt, AttemptOptions, PhaseTimer, Progress
from recon.sfm.photos import PhotoSet, prepare_photos
from recon.sfm.retrieval import retrieval_pairs

MATCHERS = ("auto", "exhaustive", "retrieval", "sequential")
MAPPERS = ("incremental", "global")
# exhaustive costs N^2/2 pairs; beyond this many photos, retrieval (~k N pairs) costs less
AUTO_EXHAUSTIVE_MAX_IMAGES = 40


class SfmError(RuntimeError):
    """SfM produced nothing usable; the message is one line, e.g.
    "0 of 12 images registered: not enough matches between the photos"."""


@dataclass
class SfmResult:
    """What `run_sfm` returns."""

    reconstruction: pycolmap.Reconstruction  # undistorted: PINHOLE cameras, poses, 3D points
    images_dir: Path  # undistorted images, named as in `reconstruction`
    report: dict  # plain JSON: counts, per-image reasons, errors, attempts, timings


def validate_config(config: SfmConfig) -> None:
    if config.matcher not in MATCHERS:
        raise ValueError(f"matcher must be one of {', '.join(MATCHERS)}, got {config.matcher!r}")
    if config.mapper not in MAPPERS:
        raise ValueError(f"mapper must be one of {', '.join(MAPPERS)}, got {config.mapper!r}")
    if config.max_image_size < 64 or config.max_num_features < 64:
        raise ValueError("max_image_size and max_num_features must be at least 64")
    try:
        pycolmap.CameraModelId.__members__[config.camera_model]
    except KeyError:
        raise ValueError(f"unknown COLMAP camera model {config.camera_model!r}") from None


def attempt_ladder(config: SfmConfig, num_images: int) -> list[AttemptOptions]:
    """Attempt 1 uses the config. With `try_harder`, attempt 2 re-extracts the photos left out
    with 4x more SIFT features, a lower peak threshold and 2x upsampling (finer, fainter
    blobs), matches them against every photo and relaxes the verification and registration
    thresholds; attempt 3 re-matches them with guided matching and, if attempt 1 did not
    match exhaustively, matches all pairs (up to 300 photos). See `colmap_retry`."""
    matcher = config.matcher
    if matcher == "auto":
        matcher = "exhaustive" if num_images <= AUTO_EXHAUSTIVE_MAX_IMAGES else "retrieval"
    first = AttemptOptions(
        name="defaults",
        max_image_size=config.max_image_size,
        max_num_features=config.max_num_features,
        peak_threshold=steps.DEFAULT_PEAK_THRESHOLD,
        always_upsample=False,
        matcher=matcher,
        guided_matching=False,
        min_num_inliers=15,
        min_num_matches=15,
        init_min_num_inliers=100,
        abs_pose_min_num_inliers=30,
        abs_pose_min_inlier_ratio=0.25,
    )
    if not config.try_harder:
        return [first]
    second = replace(
        first,
        name="more features for the photos left out, relaxed thresholds",
        max_num_features=max(16384, 4 * config.max_num_features),
        peak_threshold=0.004,
        always_upsample=True,
        min_num_inliers=10,
        min_num_matches=10,
        init_min_num_inliers=50,
        abs_pose_min_num_inliers=15,
        abs_pose_min_inlier_ratio=0.15,
    )
    third = replace(
        second, name="guided matching, all pairs", matcher="exhaustive", guided_matching=True
    )
    return [first, second, third]


# The initial pair's parallax when no pair had COLMAP's 16 degrees: a forward-facing capture
# (LLFF's, a phone swept across a scene) has a few degrees between any two photos (llff_flower:
# no initial pair at 16 degrees in three attempts; every photo registered at 4)
LOW_PARALLAX_INIT_ANGLE = 4.0


def low_parallax(options: AttemptOptions) -> AttemptOptions | None:
    """The same attempt with the initial pair's parallax lowered to LOW_PARALLAX_INIT_ANGLE,
    or None when it already is that low. Its features and matches are the failed attempt's:
    only the mapper runs again."""
    if options.init_min_tri_angle <= LOW_PARALLAX_INIT_ANGLE:
        return None
    return replace(
        options,
        name=f"{options.name}, low-parallax initial pair",
        init_min_tri_angle=LOW_PARALLAX_INIT_ANGLE,
    )


def camera_groups(photos: PhotoSet, single_camera: bool) -> list[tuple[list[str], int]]:
    """(names, longer side px) of the images sharing one camera: all photos of one size when
    `single_camera`, else one group per photo."""
    if not single_camera:
        return [([p.name], max(p.width, p.height)) for p in photos.photos]
    groups: dict[tuple[int, int], list[str]] = {}
    for p in photos.photos:
        groups.setdefault((p.width, p.height), []).append(p.name)
    return [(names, max(size)) for size, names in groups.items()]


def extraction_key(options: AttemptOptions) -> tuple:
    return (
        options.max_image_size,
        options.max_num_features,
        options.peak_threshold,
        options.always_upsample,
    )


def prepare_retry(
    attempt: Attempt,
    previous: Attempt,
    photos: PhotoSet,
    groups: list[tuple[list[str], int]],
    config: SfmConfig,
    progress: Progress,
) -> list[tuple[str, str]]:
    """Start from the previous database; re-extract (or re-match) the photos it left out.
    Returns the pairs to match."""
    kept = diagnose.registered_names(previous.best) if previous.models else set()
    retry = [n for n in photos.names if n not in kept]
    attempt.retried, retry_set = retry, set(retry)
    colmap_retry.copy_database(previous.database, attempt.database)
    if extraction_key(attempt.options) != extraction_key(previous.options):
        colmap_retry.forget_features(attempt.database, retry)
        retry_groups = [([n for n in names if n in retry_set], side) for names, side in groups]
        steps.extract_features(
            attempt.database,
            photos.staging_dir,
            [g for g in retry_groups if g[0]],
            attempt.options,
            config.camera_model,
            config.num_threads,
            progress,
        )
    elif attempt.options.guided_matching and not previous.options.guided_matching:
        colmap_retry.forget_matches(attempt.database, retry)
    all_pairs = attempt.options.matcher == "exhaustive" and previous.options.matcher != "exhaustive"
    return colmap_retry.retry_pairs(photos.names, retry, all_pairs)


def first_pairs(
    database: Path, names: list[str], matcher: str, neighbors: int, seed: int
) -> list[tuple[str, str]]:
    """The image pairs a first attempt matches (`seed`: the retrieval vocabulary's)."""
    if matcher == "exhaustive":
        return steps.exhaustive_pairs(names)
    if matcher == "retrieval":
        return retrieval_pairs(names, steps.read_descriptors(database, names), neighbors, seed)
    return steps.sequential_pairs(names)


def run_attempt(
    options: AttemptOptions,
    index: int,
    photos: PhotoSet,
    groups: list[tuple[list[str], int]],
    work_dir: Path,
    config: SfmConfig,
    previous: Attempt | None,
    progress: Progress,
) -> Attempt:
    """Extract features, match, map: one rung of the ladder (a retry when `previous`)."""
    directory = work_dir / f"attempt{index}"
    shutil.rmtree(directory, ignore_errors=True)
    directory.mkdir(parents=True)
    attempt = Attempt(options, directory, {}, PhaseTimer())
    suffix = "" if index == 1 else f" (attempt {index})"

    def report(phase: str, done: int, total: int) -> None:
        progress(phase + suffix, done, total)

    threads, names, db = config.num_threads, photos.names, attempt.database
    with attempt.timer("features"):
        if previous is not None:
            pairs = prepare_retry(attempt, previous, photos, groups, config, report)
        else:
            steps.extract_features(
                db, photos.staging_dir, groups, options, config.camera_model, threads, report
            )
            pairs = first_pairs(db, names, options.matcher, config.retrieval_neighbors, config.seed)
    with attempt.timer("matching"):
        attempt.pairs_matched = len(pairs)
        steps.match_pairs(db, directory, pairs, options, config.seed, threads, report)
    if previous is None and (lower := low_parallax(options)) is not None:
        with attempt.timer("parallax"):
            angles = diagnose.pair_parallax(db, options.init_min_num_inliers)
        attempt.max_pair_parallax = float(angles.max()) if len(angles) else None
        if len(angles) and angles.max() < options.init_min_tri_angle:
            # no pair could start the model: map with the lower angle now, not after a failure
            options = attempt.options = replace(lower, name=f"{lower.name} (pairs' parallax)")
    with attempt.timer("mapping"):
        attempt.models = steps.map_images(
            db,
            photos.staging_dir,
            directory / "sparse",
            names,
            config.mapper,
            options,
            config.seed,
            threads,
            report,
        )
    return attempt


def run_ladder(
    photos: PhotoSet, work_dir: Path, config: SfmConfig, progress: Progress
) -> list[Attempt]:
    """Run attempts until one registers every photo or the ladder ends."""
    groups = camera_groups(photos, config.single_camera)
    attempts: list[Attempt] = []
    ladder = attempt_ladder(config, len(photos.photos))
    while ladder:
        options = ladder.pop(0)
        previous = attempts[-1] if attempts else None
        index = len(attempts) + 1
        attempt = run_attempt(options, index, photos, groups, work_dir, config, previous, progress)
        attempts.append(attempt)
        if attempt.registered == len(photos.photos):
            break
        if attempt.options.init_min_tri_angle < options.init_min_tri_angle:  # lowered up front
            angle = attempt.options.init_min_tri_angle
            ladder = [replace(o, init_min_tri_angle=angle) for o in ladder]
        elif attempt.registered < min(3, len(photos.photos)) and (lower := low_parallax(options)):
            # no model at all: first the same matches with less parallax for the initial
            # pair, then the ladder (which keeps the lower angle)
            ladder = [lower] + [
                replace(o, init_min_tri_angle=lower.init_min_tri_angle) for o in ladder
            ]
    return attempts


def run_sfm(
    image_dir: Path,
    work_dir: Path,
    config: SfmConfig = SfmConfig(),  # noqa: B008 (frozen: one shared default is safe)
    progress: Progress | None = None,
) -> SfmResult:
    """Photos in `image_dir` -> undistorted PINHOLE reconstruction, images and report.

    `work_dir` receives images/ (staged photos), attempt<k>/ (database and models of each
    attempt), sparse_best/ (the kept model, original camera model) and undistorted/ (images/,
    sparse/). `progress(phase, done, total)` is called as each phase advances.
    Raises PhotoError (a ValueError) for bad input folders, SfmError when nothing registers.
    """
    validate_config(config)
    progress = progress or (lambda phase, done, total: None)
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    timer, start = PhaseTimer(), time.perf_counter()
    with steps.glog_level(config.verbose):
        pycolmap.set_random_seed(config.seed)
        with timer("photos"):
            photos = prepare_photos(Path(image_dir), work_dir / "images", config.min_image_side)
        attempts = run_ladder(photos, work_dir, config, progress)
        chosen = max(
            attempts, key=lambda a: (a.registered, a.best.num_points3D() if a.models else 0)
        )
        if chosen.registered < min(3, len(photos.photos)):
            raise SfmError(failure_message(chosen, photos))
        with timer("refinement"):
            refinement = steps.refine_intrinsics(chosen.best, config.refine_principal_point)
        with timer("undistortion"):
            progress("undistortion", 0, 1)
            undistorted = steps.undistort(
                chosen.best, photos.staging_dir, work_dir, config.num_threads
            )
            reconstruction = pycolmap.Reconstruction(undistorted / "sparse")
            progress("undistortion", 1, 1)
    for attempt in attempts:
        for phase in attempt.timer.wall:
            timer.wall[phase] = timer.wall.get(phase, 0.0) + attempt.timer.wall[phase]
            timer.cpu[phase] = timer.cpu.get(phase, 0.0) + attempt.timer.cpu[phase]
    report = build_report(config, photos, attempts, chosen, reconstruction, timer)
    report["intrinsics_refinement"] = refinement
    report["total_wall_s"] = round(time.perf_counter() - start, 2)
    report["paths"] = {
        "database": str(chosen.database),
        "sparse_distorted": str(work_dir / "sparse_best"),
        "undistorted": str(undistorted),
    }
    return SfmResult(reconstruction, undistorted / "images", report)


def failure_message(attempt: Attempt, photos: PhotoSet) -> str:
    """One line: how many registered, and the most common cause among the others."""
    n = len(photos.photos)
    stats = diagnose.image_match_stats(attempt.database, attempt.options.min_num_inliers)
    featureless = sum(s.num_keypoints < diagnose.MIN_KEYPOINTS for s in stats.values())
    unverified = sum(s.num_verified_pairs == 0 for s in stats.values())
    if featureless > n // 2:
        cause = f"{featureless} images have no usable features (blank, blurred or dark photos?)"
    elif unverified > n // 2:
        cause = "not enough matches between the photos (do they overlap?)"
    else:
        cause = "no initial pair could be reconstructed (too little parallax or too few matches)"
    return f"{attempt.registered} of {n} images registered: {cause}"
