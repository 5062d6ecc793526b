"""`recon sfm PHOTOS|VIDEO`: run the pycolmap engine in a scratch folder inside the workspace,
then write its undistorted model as the workspace scene (same outputs as the pose import).

Videos (a video file, or the videos of a folder next to its photos) are first cut into
frames in the scratch folder (`video_extract`); the frames and the photos go through the
photo pipeline together, matched sequentially, and the frames are kept in WS/sfm/frames/.
Nothing in the workspace changes until the whole stage has succeeded.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
import time
from pathlib import Path

from recon.sfm.colmap_sfm import SfmConfig, run_sfm
from recon.sfm.photos import PhotoError, list_photo_files
from recon.sfm.scene_writer import SceneConfig
from recon.sfm.sources import read_colmap
from recon.sfm.stage import write_sfm_stage
from recon.sfm.video import VIDEO_SUFFIXES, VideoConfig, is_video, validate_video_config
from recon.sfm.video_extract import VideoFrames, extract_videos, video_report
from recon.workspace import Workspace
from recon.workspace.registration import registration_summary


def video_files(source: Path) -> list[Path]:
    """The videos of the input: [source] for a video file, a folder's videos (sorted), or
    [] for a folder of photos. PhotoError for a missing source or a file that is no video."""
    source = Path(source)
    if source.is_file():
        if not is_video(source.name):
            raise PhotoError(
                f"{source} is neither a folder nor a video ({', '.join(VIDEO_SUFFIXES)})"
            )
        return [source]
    return [f for f in list_photo_files(source) if is_video(f.name)]


def sfm_config(options: dict, videos: list[Path]) -> SfmConfig:
    """The engine's config from the CLI options; the auto matcher is sequential for video
    frames (ordered: each overlaps its neighbours, so N x ~20 pairs instead of N^2 / 2)."""
    fields = {f.name for f in dataclasses.fields(SfmConfig)}
    values = {k: v for k, v in options.items() if k in fields and v is not None}
    if videos and values.get("matcher", "auto") == "auto":
        values["matcher"] = "sequential"
    return SfmConfig(**values)


def link_inputs(photos: list[Path], frames: list[Path], folder: Path) -> None:
    """One flat folder of symlinks holding the photos and the video frames for the engine."""
    folder.mkdir(parents=True)
    for f in [*photos, *frames]:
        target = folder / f.name
        if target.is_symlink():
            raise PhotoError(f"{f.name} is both a photo and a video frame name: rename the photo")
        os.symlink(f.resolve(), target)


def videos_summary(videos: list[VideoFrames], config: VideoConfig, wall_s: float) -> dict:
    """The `video` section of the sfm report: counts, time, then one entry per video."""
    reports = [video_report(v) for v in videos]
    decoded = sum(r["frames_decoded"] for r in reports)
    chosen = sum(r["windows"] for r in reports)
    kept = sum(r["frames_kept"] for r in reports)
    return {
        "config": dataclasses.asdict(config),
        "videos_given": len(videos),
        "frames_decoded": decoded,
        "frames_chosen": chosen,
        "frames_kept": kept,
        "frames_blurred": chosen - kept,
        "extraction_wall_s": round(wall_s, 2),
        "videos": reports,
    }


def photos_to_workspace(
    images: Path,
    ws: Workspace,
    cfg: SceneConfig,
    options: dict,
    progress,
    video_config: VideoConfig | None = None,
) -> dict:
    """SfM on a photo folder, a video, or a folder of both -> the workspace's sfm stage."""
    videos = video_files(images)
    config = sfm_config(options, videos)
    work = Path(tempfile.mkdtemp(prefix=".sfm-work-", dir=ws.root))
    try:
        with ws.writer_lock("sfm-engine"):
            if not videos:
                return engine_to_workspace(
                    Path(images), images, ws, cfg, config, work, progress, {"source": "photos"}, {}
                )
            video = video_config or VideoConfig()
            validate_video_config(video)
            frames_dir, started = work / "frames", time.perf_counter()
            extracted = extract_videos(videos, frames_dir, video, progress, config.verbose)
            extract_s = time.perf_counter() - started
            others = (
                []
                if Path(images).is_file()
                else [f for f in list_photo_files(images) if not is_video(f.name)]
            )
            link_inputs(
                others, [frames_dir / n for v in extracted for n in v.names], work / "input"
            )
            record = {
                "source": "video" if not others else "photos+video",
                **dataclasses.asdict(video),
            }
            return engine_to_workspace(
                work / "input",
                images,
                ws,
                cfg,
                config,
                work,
                progress,
                record,
                {"video": videos_summary(extracted, video, extract_s)},
                {str(ws.frames_dir.relative_to(ws.sfm_dir)): frames_dir},
            )
    finally:
        shutil.rmtree(work, ignore_errors=True)


def engine_to_workspace(
    image_dir: Path,
    source: Path,
    ws: Workspace,
    cfg: SceneConfig,
    config: SfmConfig,
    work: Path,
    progress,
    record: dict,
    extra_report: dict,
    extra_copies: dict[str, Path] | None = None,
) -> dict:
    """Run the engine on `image_dir` in `work/colmap`, then write and record the sfm stage with
    `source` (the user's photo folder or video) as its input."""
    result = run_sfm(image_dir, work / "colmap", config, progress)
    posed = read_colmap(result.images_dir.parent / "sparse", result.images_dir, cfg.holdout_every)
    posed.source = str(source)
    keep = {
        "colmap/database.db": Path(result.report["paths"]["database"]),
        "colmap/sparse": Path(result.report["paths"]["sparse_distorted"]),
    }
    keep = {k: v for k, v in keep.items() if v.exists()} | (extra_copies or {})
    report = {k: v for k, v in result.report.items() if k != "paths"} | extra_report
    report["registration"] = registration_summary(report, config.min_registered)
    label = "video" if Path(source).is_file() else "photos"
    return write_sfm_stage(
        ws,
        posed,
        cfg,
        {label: Path(source)},
        {**record, **dataclasses.asdict(config)},
        report,
        progress,
        copy_into_sfm=keep,
    )
