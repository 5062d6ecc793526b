"""Structure from motion over pycolmap: photos in, a registered and undistorted (PINHOLE)
reconstruction plus a report out.

Phases: photo validation and staging (`photos.py`), SIFT extraction, pair matching with
two-view verification, incremental (or global) mapping with bundle adjustment, keeping the
largest model, undistortion. When photos stay unregistered the engine tries harder on its own
(more features and relaxed thresholds, then another matcher with guided matching) and keeps
the best attempt; the report says which images are still out and why.
"""

from __future__ import annotations

import contextlib
import shutil
import time
import zlib  # noqa: F401  (before pycolmap: importing pycolmap first corrupts zlib's heap)
from dataclasses import dataclass, replace
from pathlib import Path

import pycolmap

from recon.sfm import colmap_diagnose as diagnose
from recon.sfm import colmap_steps as steps
from recon.sfm.colmap_report import build_report
from recon.sfm.colmap_steps import AttemptOptions, Progress
from recon.sfm.photos import PhotoSet, prepare_photos

MATCHERS = ("auto", "exhaustive", "sequential")
MAPPERS = ("incremental", "global")
AUTO_EXHAUSTIVE_MAX_IMAGES = 100  # exhaustive costs N^2/2 pairs; beyond this, sequential
TRY_HARDER_EXHAUSTIVE_MAX_IMAGES = 300  # the third attempt's exhaustive matching stops here


class SfmError(RuntimeError):
    """SfM produced nothing usable; the message is one line, e.g.
    "0 of 12 images registered: not enough matches between the photos"."""


@dataclass(frozen=True)
class SfmConfig:
    """Options of `run_sfm` (one CLI flag each; the comment after a field is its help).

    SIFT keypoints found on the downscaled image are rescaled to full resolution, so
    `max_image_size` trades extraction time and small-detail features, not pose precision
    directly. Matching cost grows with `max_num_features` squared per pair.
    """

    max_image_size: int = 1200  # SIFT runs on photos downscaled to this longer side (px)
    max_num_features: int = 4096  # SIFT keypoints kept per image
    matcher: str = "auto"  # auto | exhaustive | sequential (auto: exhaustive up to 100 photos)
    mapper: str = "incremental"  # incremental (COLMAP) | global (GLOMAP)
    camera_model: str = "SIMPLE_RADIAL"  # COLMAP camera model: SIMPLE_RADIAL, OPENCV, PINHOLE...
    single_camera: bool = True  # one camera shared by all photos of one size (one device)
    try_harder: bool = True  # retry with more features / other matcher if photos stay out
    min_image_side: int = 64  # photos with a shorter side below this (px) are skipped
    seed: int = 0  # RANSAC and mapper seed (runs repeat exactly only with num_threads=1)
    num_threads: int = -1  # COLMAP threads (-1: all cores)
    verbose: bool = False  # show COLMAP's own log lines


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
    """Attempt 1 uses the config; with `try_harder`, attempt 2 extracts 4x more features with
    a lower SIFT peak threshold and relaxes the verification and registration thresholds,
    attempt 3 keeps those features and switches matcher (exhaustive instead of sequential,
    up to 300 images) with guided matching."""
    matcher = config.matcher
    if matcher == "auto":
        matcher = "exhaustive" if num_images <= AUTO_EXHAUSTIVE_MAX_IMAGES else "sequential"
    first = AttemptOptions(
        name="defaults",
        max_image_size=config.max_image_size,
        max_num_features=config.max_num_features,
        peak_threshold=steps.DEFAULT_PEAK_THRESHOLD,
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
        name="more features, relaxed thresholds",
        max_num_features=max(16384, 4 * config.max_num_features),
        max_image_size=max(config.max_image_size, 1600),
        peak_threshold=0.004,
        min_num_inliers=10,
        min_num_matches=10,
        init_min_num_inliers=50,
        abs_pose_min_num_inliers=15,
        abs_pose_min_inlier_ratio=0.15,
    )
    if matcher == "sequential" and num_images > TRY_HARDER_EXHAUSTIVE_MAX_IMAGES:
        return [first, second]
    third = replace(
        second, name="exhaustive + guided matching", matcher="exhaustive", guided_matching=True
    )
    return [first, second, third]


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


def camera_groups(photos: PhotoSet, single_camera: bool) -> list[list[str]]:
    """Images sharing one camera: all photos of one size when `single_camera`, else one each."""
    if not single_camera:
        return [[p.name] for p in photos.photos]
    groups: dict[tuple[int, int], list[str]] = {}
    for p in photos.photos:
        groups.setdefault((p.width, p.height), []).append(p.name)
    return list(groups.values())


def reuse_features(attempts: list[Attempt], options: AttemptOptions, database: Path) -> bool:
    """Copy the database of an earlier attempt with the same extraction settings, minus its
    matches, so a matcher-only change does not re-extract features."""
    key = (options.max_image_size, options.max_num_features, options.peak_threshold)
    for earlier in attempts:
        o = earlier.options
        if (o.max_image_size, o.max_num_features, o.peak_threshold) == key:
            shutil.copyfile(earlier.database, database)
            db = pycolmap.Database.open(database)
            db.clear_matches()
            db.clear_two_view_geometries()
            db.close()
            return True
    return False


def run_attempt(
    options: AttemptOptions,
    index: int,
    photos: PhotoSet,
    groups: list[list[str]],
    work_dir: Path,
    config: SfmConfig,
    earlier: list[Attempt],
    progress: Progress,
) -> Attempt:
    """Extract (or reuse) features, match, map: one rung of the ladder."""
    directory = work_dir / f"attempt{index}"
    shutil.rmtree(directory, ignore_errors=True)
    directory.mkdir(parents=True)
    attempt = Attempt(options, directory, {}, PhaseTimer())
    suffix = "" if index == 1 else f" (attempt {index})"

    def report(phase: str, done: int, total: int) -> None:
        progress(phase + suffix, done, total)

    threads, names = config.num_threads, photos.names
    with attempt.timer("features"):
        if not reuse_features(earlier, options, attempt.database):
            steps.extract_features(
                attempt.database,
                photos.staging_dir,
                groups,
                options,
                config.camera_model,
                threads,
                report,
            )
    with attempt.timer("matching"):
        pairs = (
            steps.exhaustive_pairs(names)
            if options.matcher == "exhaustive"
            else steps.sequential_pairs(names)
        )
        steps.match_pairs(attempt.database, directory, pairs, options, config.seed, threads, report)
    with attempt.timer("mapping"):
        attempt.models = steps.map_images(
            attempt.database,
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


def run_sfm(
    image_dir: Path,
    work_dir: Path,
    config: SfmConfig = SfmConfig(),
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
        groups = camera_groups(photos, config.single_camera)
        attempts: list[Attempt] = []
        for index, options in enumerate(attempt_ladder(config, len(photos.photos)), start=1):
            attempts.append(
                run_attempt(options, index, photos, groups, work_dir, config, attempts, progress)
            )
            if attempts[-1].registered == len(photos.photos):
                break
        chosen = max(
            attempts, key=lambda a: (a.registered, a.best.num_points3D() if a.models else 0)
        )
        if chosen.registered < min(3, len(photos.photos)):
            raise SfmError(failure_message(chosen, photos))
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
