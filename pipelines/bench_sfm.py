"""Benchmark the SfM engine on the fox capture against its reference COLMAP poses.

    python pipelines/bench_sfm.py [--images ../shared/data/fox/images] [--out bench/results/sfm_fox.json]

Runs `run_sfm` with the default config (flags override it), matches registered images to the
reference frames of transforms.json by file name, aligns the camera centres with a Sim3
(ATE) and removes the one common camera-frame rotation a different principal point would
cause (both the reference and recon refine it now), then writes registered count,
median rotation / centre errors, time per phase and total wall time as JSON. The machine's
load average is recorded too: other jobs sharing the cores stretch wall time, not CPU time.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import click
import numpy as np

import recon  # noqa: F401  (before pycolmap: recon imports zlib first)
from recon.cameras.conventions import opencv_c2w_from_opengl_c2w
from recon.io.atomic import atomic_write_json
from recon.metrics.pose import pose_errors
from recon.sfm.colmap_sfm import SfmConfig, run_sfm

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "fox"


def reference_poses(transforms: Path) -> dict[str, np.ndarray]:
    """file name -> (4, 4) OpenCV world_from_cam from an instant-ngp transforms.json."""
    meta = json.loads(transforms.read_text())
    return {
        Path(f["file_path"]).name: opencv_c2w_from_opengl_c2w(
            np.asarray(f["transform_matrix"], float)
        )
        for f in meta["frames"]
    }


def estimated_poses(reconstruction) -> dict[str, np.ndarray]:
    """image name -> (4, 4) world_from_cam of every registered image."""
    poses = {}
    for image in reconstruction.images.values():
        if image.has_pose:
            world_from_cam = np.eye(4)
            world_from_cam[:3] = image.cam_from_world().inverse().matrix()
            poses[image.name] = world_from_cam
    return poses


def accuracy(estimated: dict[str, np.ndarray], reference: dict[str, np.ndarray]) -> dict:
    names = sorted(set(estimated) & set(reference))
    if len(names) < 3:
        return {"compared_images": len(names)}
    errors = pose_errors(
        np.stack([estimated[n] for n in names]),
        np.stack([reference[n] for n in names]),
        remove_common_rotation=True,
    )
    worst = int(np.argmax(errors["rotation_error_deg"]))
    return {
        "compared_images": len(names),
        **{k: round(v, 5) for k, v in errors.items() if isinstance(v, float)},
        "max_rotation_error_deg": round(float(errors["rotation_error_deg"].max()), 5),
        "max_center_error_pct": round(float(errors["center_error_pct"].max()), 5),
        "worst_rotation_image": names[worst],
    }


@click.command()
@click.option(
    "--images", type=click.Path(path_type=Path), default=DATA / "images", show_default=True
)
@click.option(
    "--transforms",
    type=click.Path(path_type=Path),
    default=DATA / "transforms.json",
    show_default=True,
)
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    default=Path("bench/results/sfm_fox.json"),
    show_default=True,
)
@click.option(
    "--work",
    type=click.Path(path_type=Path),
    default=None,
    help="Keep COLMAP's files here (default: a temporary folder).",
)
@click.option("--max-image-size", type=int, default=None)
@click.option("--max-num-features", type=int, default=None)
@click.option("--matcher", default=None)
@click.option("--mapper", default=None)
@click.option("--num-threads", type=int, default=None)
def main(images, transforms, out, work, **overrides) -> None:
    config = replace(SfmConfig(), **{k: v for k, v in overrides.items() if v is not None})
    load_before = os.getloadavg()
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        result = run_sfm(images, work or Path(tmp), config)
        wall = time.perf_counter() - start
    report = result.report
    results = {
        "dataset": str(images),
        "config": report["config"],
        "images_given": report["images_given"],
        "images_registered": report["images_registered"],
        "unregistered": report["unregistered"],
        "accuracy_vs_reference": accuracy(
            estimated_poses(result.reconstruction), reference_poses(transforms)
        ),
        "mean_reprojection_error_px": round(report["mean_reprojection_error_px"], 4),
        "points3d": report["points3d"],
        "attempts": [
            {k: a[k] for k in ("name", "registered", "wall_s", "cpu_s")} for a in report["attempts"]
        ],
        "phases": report["phases"],
        "total_wall_s": round(wall, 2),
        "load_average_1min_before_after": [round(load_before[0], 2), round(os.getloadavg()[0], 2)],
        "cpu_count": os.cpu_count(),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out, results)
    click.echo(
        json.dumps(
            {
                k: results[k]
                for k in (
                    "images_registered",
                    "accuracy_vs_reference",
                    "phases",
                    "total_wall_s",
                    "load_average_1min_before_after",
                )
            }
        )
    )


if __name__ == "__main__":
    main()
