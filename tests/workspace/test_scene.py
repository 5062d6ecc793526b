"""The workspace's image pyramid: built once per level from the sfm images by area resampling,
rebuilt when sfm reruns, and used by train / eval / render at the run's level."""

import json
import os

import numpy as np
import pytest
import torch

from recon.io.images import read_image, resize_area
from recon.workspace import Workspace
from recon.workspace.scene import (
    ensure_pyramid_level,
    level_size,
    load_images,
    load_images_and_alpha,
    load_scene,
)
from tests.conftest import recon_cli, sphere_workspace


@pytest.fixture(scope="module")
def ws_root(tmp_path_factory):
    return sphere_workspace(tmp_path_factory.mktemp("pyramid"), n_train=4, n_test=2, size=24)


def test_level_size_worked_example():
    assert level_size(1076, 1913, 4) == (269, 478)
    assert level_size(200, 200, 1) == (200, 200)
    assert level_size(3, 5, 8) == (1, 1)


def test_level_is_the_area_resampled_sfm_image_and_is_built_once(ws_root):
    ws = Workspace.open(ws_root)
    scene = load_scene(ws, with_points=False)
    ensure_pyramid_level(ws, scene, 3)
    level = ws.pyramid_dir(3)
    manifest = json.loads((level / "pyramid.json").read_text())
    assert manifest["downscale"] == 3
    f = scene.frames[0]
    full = read_image(ws.resolve(f["image"]))  # RGBA: the synthetic sphere's photos had alpha
    small = read_image(ws.level_image(f["image"], 3))
    assert full.shape[-1] == 4 and small.shape == (8, 8, 4)  # the level keeps the alpha
    assert np.abs(small - resize_area(full, 8, 8)).max() <= 1 / 255 + 1e-6  # 8-bit PNG rounding
    stamp = os.stat(level / "pyramid.json").st_mtime_ns
    ensure_pyramid_level(ws, scene, 3)  # current: not rebuilt
    assert os.stat(level / "pyramid.json").st_mtime_ns == stamp
    imgs = load_images(ws, scene, scene.split("test"), 3)
    cams = scene.cameras(scene.split("test"), downscale=3)
    assert tuple(imgs.shape) == (2, 8, 8, 3) and cams.width.tolist() == [8, 8]
    rgb, alpha = load_images_and_alpha(ws, scene, scene.split("test"), 3)
    assert torch.equal(rgb, imgs) and tuple(alpha.shape) == (2, 8, 8)
    assert 0 < float(alpha.mean()) < 1
    assert cams.K[0, 0, 2].item() == pytest.approx(f["cx"] / 3)


def test_a_rerun_of_sfm_makes_the_level_stale(ws_root, tmp_path):
    ws = Workspace.open(ws_root)
    scene = load_scene(ws, with_points=False)
    ensure_pyramid_level(ws, scene, 2)
    doc = json.loads(ws.cameras_json.read_text())
    before = json.loads((ws.pyramid_dir(2) / "pyramid.json").read_text())["source"]
    ws.cameras_json.write_text(
        json.dumps(doc) + "\n"
    )  # what a new sfm run does: a new cameras.json
    ensure_pyramid_level(ws, scene, 2)
    after = json.loads((ws.pyramid_dir(2) / "pyramid.json").read_text())["source"]
    assert before != after


def test_train_eval_render_at_levels_through_the_cli(ws_root):
    ws = str(ws_root)
    recon_cli(
        "train",
        "-w",
        ws,
        "--method",
        "3dgs",
        "--run",
        "half",
        "--steps",
        "5",
        "--downscale",
        "2",
        "--eval-views",
        "1",
        "--threads",
        "1",
    )
    run = json.loads((ws_root / "runs" / "half" / "run.json").read_text())
    assert run["resolution"]["working"] == {
        "downscale": 2,
        "width": 12,
        "height": 12,
        "source": "downscale",
        "reason": "--downscale 2 was given",
    }
    out = json.loads(recon_cli("eval", "-w", ws, "--run", "half", "--no-lpips", "--json").stdout)[
        "half"
    ]
    assert out["resolution"] == [12, 12] and out["downscale"] == 2  # the run's level by default
    full = json.loads(
        recon_cli(
            "eval", "-w", ws, "--run", "half", "--no-lpips", "--downscale", "1", "--json"
        ).stdout
    )["half"]
    assert full["resolution"] == [24, 24] and full["rendered_at"]["downscale"] == 1
    assert "psnr_border" in full["mean"]
    r = json.loads(
        recon_cli("render", "-w", ws, "--run", "half", "--max-side", "20", "--json").stdout
    )
    assert r["resolution"] == [12, 12] and r["rendered_at"]["size"] == [12, 12]
    report = (ws_root / "report.md").read_text()
    assert "| half | 3dgs | 12×12 |" in report
    bad = recon_cli(
        "train",
        "-w",
        ws,
        "--method",
        "3dgs",
        "--run",
        "x",
        "--steps",
        "5",
        "--downscale",
        "2",
        "--max-side",
        "10",
        check=False,
    )
    assert (
        bad.returncode != 0 and "not both" in bad.stderr and not (ws_root / "runs" / "x").exists()
    )


def test_periodic_psnr_of_3dgs_renders_at_the_training_level(ws_root):
    """The periodic held-out PSNR compares with photos of a coarser level (--eval-max-side); 3dgs
    renders those views at its training level and area-downsamples (it aliases when minified)."""
    ws = str(ws_root)
    recon_cli(
        "train", "-w", ws, "--method", "3dgs", "--run", "full", "--steps", "2", "--downscale",
        "1", "--eval-views", "1", "--eval-max-side", "16", "--threads", "1",
    )  # fmt: skip
    run = json.loads((ws_root / "runs" / "full" / "run.json").read_text())
    assert run["resolution"]["periodic_eval"] == {
        "downscale": 2,
        "size": [12, 12],
        "rendered_at_downscale": 1,
    }
