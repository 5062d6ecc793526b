"""Generate `spiral-300`: 300 ordered photos at 800 x 600 of the sample scene with exact poses,
the project's own many-photo capture for the SfM benchmark (`recon sfm` on hundreds of photos).

    python pipelines/make_capture.py [--out bench/work/data/spiral-300] [--count 300]

A photographer's walk: three turns around the still life of `sample_data/` (same scene, same
texture seed), the camera raised from 25 to 60 degrees of elevation by the middle of the walk
and lowered back, stepping out to 2.1 m and in to 1.7 m (`recon.synthetic.scene.spiral_cameras`);
the last photos meet the first ones, so the path closes a loop. Pinhole f = 960 px (45 degree
horizontal field of view, as sample_data), no distortion, one sample per pixel, composited on
white, written as JPEG (quality 95) like a camera's photos; transforms.json holds the poses
(OpenGL camera-to-world) for `pipelines/bench_sfm.py --transforms`. Same arguments -> same files.
~0.6 s a photo on one core.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import click
import torch

from recon.cameras.conventions import opengl_c2w_from_opencv_c2w
from recon.io.atomic import atomic_write_json
from recon.io.images import composite, write_jpeg
from recon.synthetic.scene import (
    SceneConfig,
    build_scene,
    make_texture,
    render_view,
    spiral_cameras,
)

ROOT = Path(__file__).resolve().parents[1]
WIDTH, HEIGHT, FOCAL = 800, 600, 960.0
TURNS, ELEVATIONS_DEG, RADII = 3.0, (25.0, 60.0), (1.7, 2.1)


def generate(out: Path, count: int, log=print) -> dict:
    scene = SceneConfig()
    mesh, texture = build_scene(scene), make_texture(scene.seed)
    x, y, z = scene.plate_center
    cameras = spiral_cameras((x, y, z), count, TURNS, ELEVATIONS_DEG, RADII, FOCAL, WIDTH, HEIGHT)
    started, frames = time.perf_counter(), []
    for i in range(count):
        name = f"images/p_{i:04d}.jpg"
        if not (out / name).exists():  # resumable: a photo once written is final
            rgba, _ = render_view(mesh, texture, scene, cameras, i, supersample=1)
            write_jpeg(out / name, composite(rgba.numpy(), (1.0, 1.0, 1.0)))
        world_from_cam = cameras.world_from_cam[i].numpy()
        frames.append(
            {
                "file_path": name,
                "transform_matrix": opengl_c2w_from_opencv_c2w(world_from_cam).tolist(),
            }
        )
        if (i + 1) % 25 == 0:
            log(f"{i + 1}/{count} photos, {time.perf_counter() - started:.0f} s")
    meta = {
        "camera_model": "OPENCV",
        "fl_x": FOCAL,
        "fl_y": FOCAL,
        "cx": WIDTH / 2,
        "cy": HEIGHT / 2,
        "w": WIDTH,
        "h": HEIGHT,
        "k1": 0.0,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "camera_angle_x": 2.0 * math.atan(0.5 * WIDTH / FOCAL),
        "generator": {"script": "pipelines/make_capture.py", "count": count},
        "frames": frames,
    }
    atomic_write_json(out / "transforms.json", meta)
    return {"photos": count, "seconds": round(time.perf_counter() - started, 1)}


@click.command()
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    default=ROOT / "bench" / "work" / "data" / "spiral-300",
    show_default=True,
)
@click.option("--count", type=int, default=300, show_default=True)
def main(out: Path, count: int) -> None:
    """Render the spiral capture of the sample scene with exact poses."""
    torch.set_num_threads(1)
    click.echo(json.dumps(generate(out, count)))


if __name__ == "__main__":
    main()
