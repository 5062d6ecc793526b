"""`recon sfm`: camera poses + sparse points into WS/sfm/ (from photos or known poses)."""

from __future__ import annotations

import contextlib
import shutil
import sys
from pathlib import Path

import click

from recon.cli.common import emit_json, json_option, workspace_option
from recon.cli.progress import Progress
from recon.options import config_field, config_option, field_help, from_options
from recon.sfm.colmap_config import SfmConfig
from recon.sfm.scene_writer import SceneConfig
from recon.sfm.sources import SourceError, read_colmap, read_llff, read_transforms
from recon.sfm.stage import write_sfm_stage
from recon.workspace import Workspace
from recon.workspace.registration import partial_warning


@contextlib.contextmanager
def new_or_existing_workspace(root: Path):
    """Open/create the workspace; if this command created it and then fails, remove it again,
    so a failed first command leaves the disk as it was."""
    existed = (root / Workspace.JSON_NAME).exists()
    root_existed = root.exists()
    ws = Workspace.create(root)
    try:
        yield ws
    except BaseException:
        if not existed:
            if root_existed:
                (root / Workspace.JSON_NAME).unlink(missing_ok=True)
                shutil.rmtree(root / ".locks", ignore_errors=True)
            else:
                shutil.rmtree(root, ignore_errors=True)
        raise


def _photo_sfm(
    images: Path, ws: Workspace, cfg: SceneConfig, options: dict, progress: Progress, video
) -> dict:
    from recon.sfm.photo_stage import photos_to_workspace

    return photos_to_workspace(images, ws, cfg, options, progress, video)


def _video_config(images: Path, frames: int | None, fps: float | None, blur_ratio: float | None):
    """The VideoConfig of the flags (None when none was given); a flag without a video in the
    input is an error rather than silently ignored."""
    if frames is None and fps is None and blur_ratio is None:
        return None
    from recon.sfm.photo_stage import video_files
    from recon.sfm.video import VideoConfig, validate_video_config

    if not video_files(images):
        raise ValueError(f"--frames, --fps and --blur-ratio apply to videos; {images} has none")
    if frames is not None and fps is not None:
        raise ValueError("give either --frames or --fps, not both")
    default = VideoConfig()
    config = VideoConfig(
        frames=0 if fps is not None else default.frames if frames is None else frames,
        fps=0.0 if fps is None else fps,
        blur_ratio=default.blur_ratio if blur_ratio is None else blur_ratio,
    )
    validate_video_config(config)
    return config


def _video_option(name: str, **kwargs):
    """A `VideoConfig` flag whose default is None ("not given": a flag without a video in the
    input is an error, and --frames and --fps exclude each other); help and the default it
    stands for come from the config."""
    from recon.sfm.video import VideoConfig

    field = config_field(VideoConfig, name)
    help_ = f"Video: {field.metadata['help']} [default: {field.default}]"
    return click.option("--" + name.replace("_", "-"), name, default=None, help=help_, **kwargs)


def _summary_line(report: dict, root: Path) -> str:
    line = f"sfm: {report['images']} images {report['splits']} -> {root / 'sfm'}"
    video = report.get("video")
    if video:
        n = video["videos_given"]
        line += (
            f"; {n} video{'s' if n > 1 else ''}: {video['frames_decoded']} frames decoded, "
            f"{video['frames_chosen']} extracted (sharpest per window), "
            f"{video['frames_kept']} kept ({video['frames_blurred']} too blurred)"
        )
    return line


@click.command()
@click.argument("images", metavar="[PHOTOS|VIDEO]", required=False, type=click.Path(path_type=Path))
@workspace_option
@click.option(
    "--from-transforms",
    "transforms",
    type=click.Path(path_type=Path),
    help="Known poses: a transforms*.json (nerfstudio / instant-ngp / Blender) or a folder "
    "with transforms_{train,val,test}.json (its split is kept).",
)
@click.option(
    "--from-colmap",
    "colmap_dir",
    type=click.Path(path_type=Path),
    help="Known poses: a COLMAP sparse model folder (text or binary).",
)
@click.option(
    "--from-llff",
    "llff_dir",
    type=click.Path(path_type=Path),
    help="Known poses: an LLFF capture (poses_bounds.npy, as the LLFF and Mip-NeRF 360 "
    "releases; every 8th photo held out).",
)
@click.option(
    "--images",
    "colmap_images",
    type=click.Path(path_type=Path),
    help="With --from-colmap: the images folder (default: next to the model); with "
    "--from-llff: the photos (default: images, images_2, images_4 or images_8 beside it).",
)
@config_option(SceneConfig, "downscale", type=click.IntRange(1, 64))
@config_option(SceneConfig, "background")
@config_option(SceneConfig, "scene")
@config_option(SceneConfig, "holdout_every", type=click.IntRange(2, 1000))
@config_option(SfmConfig, "max_image_size", type=click.IntRange(64))
@config_option(SfmConfig, "max_num_features", type=click.IntRange(64))
@config_option(SfmConfig, "matcher")
@config_option(SfmConfig, "retrieval_neighbors", type=click.IntRange(1))
@config_option(SfmConfig, "mapper")
@config_option(SfmConfig, "camera_model")
@config_option(
    SfmConfig, "refine_principal_point", "--refine-principal-point/--fixed-principal-point"
)
@config_option(SfmConfig, "single_camera", "--single-camera/--multi-camera")
@config_option(SfmConfig, "try_harder")
@config_option(SfmConfig, "min_image_side", type=click.IntRange(1))
@config_option(SfmConfig, "min_registered", type=click.FloatRange(0.0, 1.0))
@click.option(
    "--allow-partial",
    is_flag=True,
    help="Exit 0 even when fewer than --min-registered of the photos registered.",
)
@config_option(SfmConfig, "seed")
@config_option(SfmConfig, "num_threads")
@_video_option("frames", type=int)
@_video_option("fps", type=float)
@_video_option("blur_ratio", type=float)
@json_option
@click.pass_context
def sfm(
    ctx,
    images,
    workspace,
    transforms,
    colmap_dir,
    llff_dir,
    colmap_images,
    frames,
    fps,
    blur_ratio,
    allow_partial,
    as_json,
    **options,
):
    """Camera poses and sparse points -> WS/sfm/ (COLMAP model, cameras.json, points.ply, report).

    \b
    recon sfm PHOTOS -w WS                      structure from motion (COLMAP via pycolmap)
    recon sfm VIDEO|FOLDER -w WS [--frames N]   ... on frames of a video (or of a folder's videos)
    recon sfm --from-transforms F|DIR -w WS     known poses (transforms*.json)
    recon sfm --from-colmap MODEL -w WS         known poses (COLMAP model)
    recon sfm --from-llff DIR -w WS             known poses (LLFF poses_bounds.npy)

    Exit codes: 0 done, 1 error (the workspace is left as it was), 2 bad usage, 3 fewer than
    --min-registered of the photos registered (the model is written; --allow-partial: 0).
    """
    sources = [x for x in (images, transforms, colmap_dir, llff_dir) if x is not None]
    if len(sources) != 1:
        raise click.UsageError(
            "give exactly one of IMAGES, --from-transforms, --from-colmap, --from-llff"
        )
    if colmap_images is not None and colmap_dir is None and llff_dir is None:
        raise click.UsageError("--images goes with --from-colmap or --from-llff")
    cfg = from_options(SceneConfig, options)
    holdout_every = cfg.holdout_every
    root = Path(workspace)
    with Progress(enabled=not as_json) as progress:
        if images is not None:
            if not images.exists():
                raise SourceError(f"photo folder or video {images} does not exist")
            video = _video_config(images, frames, fps, blur_ratio)
            options = {
                **{k: v for k, v in options.items() if k in field_help(SfmConfig)},
                "verbose": ctx.obj["verbose"],
            }
            with new_or_existing_workspace(root) as ws:
                report = _photo_sfm(images, ws, cfg, options, progress, video)
        else:
            if frames is not None or fps is not None or blur_ratio is not None:
                raise ValueError("--frames, --fps and --blur-ratio apply to video input only")
            if transforms is not None:
                posed = read_transforms(transforms, holdout_every)
                inputs = {"source": transforms}
                record = {"source": "transforms", "path": str(transforms)}
            elif llff_dir is not None:
                posed = read_llff(llff_dir, colmap_images, holdout_every)
                inputs = {"source": llff_dir}
                record = {"source": "llff", "path": str(llff_dir), **posed.extra}
            else:
                posed = read_colmap(colmap_dir, colmap_images, holdout_every)
                inputs = {"source": colmap_dir}
                record = {"source": "colmap", "path": str(colmap_dir)}
            image_dirs = sorted({f.path.parent for f in posed.frames})
            for i, d in enumerate(image_dirs):
                if not any(str(d).startswith(str(Path(p).resolve())) for p in inputs.values()):
                    inputs[f"images{i}"] = d
            with new_or_existing_workspace(root) as ws:
                report = write_sfm_stage(ws, posed, cfg, inputs, record, progress=progress)
    if as_json:
        emit_json({"workspace": str(root), **report})
    else:
        click.echo(_summary_line(report, root))
    registration = report.get("registration", {})
    if registration.get("partial"):
        click.echo(
            f"warning: {partial_warning(registration)}; the model is in {root / 'sfm'} "
            f"(reasons: {root / 'sfm' / 'report.json'})",
            err=True,
        )
        if not allow_partial:
            sys.exit(3)
