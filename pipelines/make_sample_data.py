"""Generate `sample_data/`: the project's own small synthetic scene with exact ground truth.

    python pipelines/make_sample_data.py [--out sample_data] [--seed 0]

Writes images/r_XXX.png (RGBA, alpha = coverage), depth/r_XXX.exr (metric z-depth, 0 = no
surface), mesh.ply (ground-truth mesh, metres) and transforms.json (nerfstudio / instant-ngp:
OpenGL camera-to-world, shared pinhole intrinsics). Same seed -> same files.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import click
import numpy as np
import torch

from recon.cameras import Cameras
from recon.cameras.conventions import opengl_c2w_from_opencv_c2w
from recon.io.atomic import atomic_path, atomic_write_json
from recon.io.exr import write_depth_exr
from recon.io.images import write_png
from recon.synthetic.scene import (
    SceneConfig,
    build_scene,
    make_texture,
    render_view,
    ring_cameras,
    scene_trimesh,
)


@dataclass(frozen=True)
class RigConfig:
    """The cameras: rings around the scene, all sharing one pinhole."""

    elevations_deg: tuple[float, ...] = (30.0, 55.0)  # one ring per elevation above the plate
    views_per_ring: int = 20  # 18 degrees between neighbours on a ring
    radius: float = 1.9  # metres from the look-at point: the objects stay in frame
    target_above_plate: float = 0.0  # look-at point: this far above the plate's top centre
    # pixels, fx = fy: 45.2 degree field of view, and COLMAP's own guess (1.2 max(w, h)) for
    # images without EXIF, so SfM starts from the right focal length
    focal: float = 240.0
    width: int = 200  # pixels
    height: int = 200  # pixels
    supersample: int = 3  # odd: samples per pixel side; alpha is the covered fraction


def make_rig(scene: SceneConfig, rig: RigConfig) -> Cameras:
    x, y, z = scene.plate_center
    target = (x, y, z + rig.target_above_plate)
    return ring_cameras(
        target, rig.radius, rig.elevations_deg, rig.views_per_ring, rig.focal, rig.width, rig.height
    )


def transforms_json(cameras: Cameras, stems: list[str], scene: SceneConfig, rig: RigConfig) -> dict:
    """nerfstudio / instant-ngp transforms: OpenGL camera-to-world, shared intrinsics."""
    K = cameras.K[0].tolist()
    world_from_cam = cameras.world_from_cam.numpy()
    frames = [
        {
            "file_path": f"images/{stem}.png",
            "depth_file_path": f"depth/{stem}.exr",
            "transform_matrix": opengl_c2w_from_opencv_c2w(world_from_cam[i]).tolist(),
        }
        for i, stem in enumerate(stems)
    ]
    return {
        "camera_model": "OPENCV",
        "fl_x": K[0][0],
        "fl_y": K[1][1],
        "cx": K[0][2],
        "cy": K[1][2],
        "w": rig.width,
        "h": rig.height,
        "k1": 0.0,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "camera_angle_x": 2.0 * math.atan(0.5 * rig.width / K[0][0]),
        "depth_unit_scale_factor": 1.0,  # depth EXRs hold metres
        "gt_mesh_path": "mesh.ply",  # recon's key for a ground-truth mesh (recon.sfm.sources)
        "generator": {
            "script": "pipelines/make_sample_data.py",
            "scene": asdict(scene),
            "rig": asdict(rig),
        },
        "frames": frames,
    }


def generate(out: Path, scene: SceneConfig, rig: RigConfig, log=print) -> dict:
    """Render every view and write the dataset under `out`; returns summary numbers."""
    started = time.perf_counter()
    mesh, texture = build_scene(scene), make_texture(scene.seed)
    cameras = make_rig(scene, rig)
    stems = [f"r_{i:03d}" for i in range(len(cameras))]
    coverage = []
    for i, stem in enumerate(stems):
        rgba, depth = render_view(mesh, texture, scene, cameras, i, rig.supersample)
        write_png(out / "images" / f"{stem}.png", rgba.numpy(), compression=9)
        write_depth_exr(out / "depth" / f"{stem}.exr", depth.numpy().astype(np.float32))
        coverage.append(float(rgba[..., 3].mean()))
        if (i + 1) % 8 == 0 or i + 1 == len(stems):
            log(f"rendered {i + 1}/{len(stems)} views, {time.perf_counter() - started:.1f} s")
    with atomic_path(out / "mesh.ply") as tmp:
        scene_trimesh(mesh, texture, scene).export(str(tmp))
    atomic_write_json(out / "transforms.json", transforms_json(cameras, stems, scene, rig))
    return {
        "views": len(stems),
        "faces": len(mesh.faces),
        "mean_coverage": float(np.mean(coverage)),
        "seconds": round(time.perf_counter() - started, 2),
    }


@click.command()
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path(__file__).resolve().parents[1] / "sample_data",
    show_default="the repository's sample_data/",
    help="Output folder (files of the same name are overwritten).",
)
@click.option("--seed", type=int, default=SceneConfig.seed, show_default=True, help="Texture seed.")
def main(out: Path, seed: int) -> None:
    """Render the synthetic sample scene with exact depth, mesh and poses."""
    torch.set_num_threads(1)  # ~2x faster than 2 threads on a shared 2-core machine
    summary = generate(out, SceneConfig(seed=seed), RigConfig())
    click.echo(json.dumps(summary))


if __name__ == "__main__":
    main()
