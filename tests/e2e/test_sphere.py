"""The whole pipeline through the real CLI on an analytic scene with known geometry:
sfm (pose import) -> train -> render -> mesh -> eval, and resume / bad-run handling."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from recon.io.exr import read_depth_exr
from tests.conftest import recon_cli, write_sphere_dataset


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("e2e")
    data = write_sphere_dataset(root / "sphere")
    ws = root / "ws"
    recon_cli("sfm", "--from-transforms", str(data), "-w", str(ws))
    recon_cli(
        "train",
        "-w",
        str(ws),
        "--method",
        "plenoxel",
        "--steps",
        "150",
        "--eval-every",
        "0.25",  # seconds of training: 150 steps take a few seconds on 2 cores
        "--eval-max-fraction",
        "0",  # the test reads the whole held-out curve
        "--eval-views",
        "2",
        "--set",
        "resolutions=24,48",
        "--set",
        "upsample_steps=80",
        "--set",
        "rays_per_batch=2048",
        "--set",
        "occupancy_res=24",
        "--set",
        "samples_per_batch=0",
        "--json",
    )
    return ws


def test_train_writes_run_log_and_model(trained):
    run = json.loads((trained / "runs" / "plenoxel" / "run.json").read_text())
    assert run["status"] == "done" and run["stop_reason"] == "steps" and run["steps"] == 150
    log = [
        json.loads(ln)
        for ln in (trained / "runs" / "plenoxel" / "log.jsonl").read_text().splitlines()
    ]
    curve = [e["test_psnr"] for e in log if "test_psnr" in e]
    assert len(curve) >= 2 and curve[-1] > 18.0, curve


def test_render_writes_png_and_metric_depth(trained):
    out = json.loads(recon_cli("render", "-w", str(trained), "--run", "plenoxel", "--json").stdout)
    assert out["frames"] == 3 and out["ms_per_frame"] > 0
    depth = read_depth_exr(trained / "runs" / "plenoxel" / "renders" / "test" / "depth" / "r_0.exr")
    gt = read_depth_exr(trained.parent / "sphere" / "test" / "r_0_depth.exr")
    both = (depth > 0) & (gt > 0)
    assert both.sum() > 50
    assert np.median(np.abs(depth[both] - gt[both])) < 0.05  # metric (original) units
    recon_cli(
        "render",
        "-w",
        str(trained),
        "--run",
        "plenoxel",
        "--path",
        "orbit",
        "--frames",
        "4",
        "--video",
    )
    assert (trained / "runs" / "plenoxel" / "renders" / "orbit" / "video.mp4").stat().st_size > 0
    # above the training size: --scale 2 renders every 2nd view at twice the side, and its
    # metric depth agrees with the 1x render's (area-downsampled) where both see the sphere
    big = json.loads(
        recon_cli(
            "render", "-w", str(trained), "--run", "plenoxel", "--scale", "2", "--every", "2",
            "--json",
        ).stdout
    )  # fmt: skip
    assert big["frames"] == 2 and big["resolution"] == [
        2 * out["resolution"][0],
        2 * out["resolution"][1],
    ]
    assert big["out"].endswith("renders/test-x2")  # the 1x renders stay
    big_depth = read_depth_exr(Path(big["out"]) / "depth" / "r_0.exr")
    assert big_depth.shape == (2 * depth.shape[0], 2 * depth.shape[1])
    small = big_depth.reshape(depth.shape[0], 2, depth.shape[1], 2).mean((1, 3))
    inside = (depth > 0) & (big_depth.reshape(depth.shape[0], 2, depth.shape[1], 2) > 0).all((1, 3))
    assert inside.sum() > 50 and np.median(np.abs(small[inside] - depth[inside])) < 0.02
    bad = recon_cli("render", "-w", str(trained), "--run", "plenoxel", "--scale", "0", check=False)
    assert bad.returncode == 2 and "--scale" in bad.stderr


def test_mesh_and_eval_against_ground_truth(trained):
    def mesh_json(*extra):
        out = recon_cli(
            "mesh", "-w", str(trained), "--run", "plenoxel", "--resolution", "64", "--json",
            "--force", *extra,
        )  # fmt: skip
        return json.loads(out.stdout)

    level_set = mesh_json("--method", "marching-cubes")
    assert level_set["method"] == "marching-cubes"
    assert 0 < level_set["visible_faces"] <= level_set["faces_before_cleanup"]
    mesh = mesh_json()  # auto: TSDF fusion for every method
    assert mesh["method"] == "tsdf" and mesh["faces"] > 100
    res = json.loads(recon_cli("eval", "-w", str(trained), "--json").stdout)["plenoxel"]
    assert res["mean"]["psnr"] > 18 and 0 < res["mean"]["ssim"] <= 1
    assert res["geometry"]["status"] == "ok" and res["geometry"]["chamfer"] < 0.1
    assert "depth_abs_rel" in res["mean"]
    assert res["speed"]["steps"] == 150
    assert (trained / "report.md").exists() and (trained / "speed_vs_error.png").stat().st_size > 0


def test_report_html_shows_the_runs_and_opens_in_a_browser(trained, tmp_path):
    """After render (an orbit video), mesh and eval: report.html links only files that exist,
    shows every held-out view four ways and the mesh previews, and a real headless browser
    loads it with no console error, no broken image and a playable video."""
    recon_cli(
        "render", "-w", str(trained), "--run", "plenoxel", "--path", "orbit", "--frames", "6",
        "--video",
    )  # fmt: skip
    recon_cli("eval", "-w", str(trained), "--run", "plenoxel")
    page = trained / "report.html"
    text = page.read_text()
    links = re.findall(r'(?:src|href)="([^"#]+)"', text)
    assert links and all((trained / link).is_file() for link in links), links
    metrics = json.loads((trained / "runs" / "plenoxel" / "eval" / "metrics.json").read_text())
    views = metrics["pictures"]
    assert views and set(views) == set(metrics["per_view"])
    for kinds in views.values():
        for kind in ("gt", "render", "error", "depth"):
            assert f'src="runs/plenoxel/eval/views/{kinds[kind]["thumb"]}"' in text
    mesh = json.loads((trained / "runs" / "plenoxel" / "mesh" / "mesh.json").read_text())
    assert len(mesh["previews"]) == 3 and "mesh/preview_0.png" in text
    assert "video.mp4" in text and "sfm_cameras.png" in text
    assert "15 registered photos</summary>" in text and "r_0 (test)" in text

    from tests.browser import open_page

    shot = tmp_path / "report.png"
    seen = open_page(page, shot)
    assert seen["images"] >= 4 * len(views) + 5, seen
    assert seen["errors"] == [] and seen["broken"] == [] and seen["bad_videos"] == [], seen
    assert shot.stat().st_size > 10_000


def test_existing_run_is_refused_and_resume_continues(trained):
    proc = recon_cli(
        "train", "-w", str(trained), "--method", "plenoxel", "--steps", "5", check=False
    )
    assert proc.returncode != 0 and "already exists" in proc.stderr
    out = json.loads(
        recon_cli(
            "train",
            "-w",
            str(trained),
            "--method",
            "plenoxel",
            "--run",
            "plenoxel",
            "--resume",
            "--steps",
            "160",
            "--json",
        ).stdout
    )
    assert out["steps"] == 160


def test_forced_rerun_that_fails_keeps_the_old_run(trained):
    before = (trained / "runs" / "plenoxel" / "model.pt").read_bytes()
    record = json.loads((trained / "workspace.json").read_text())["stages"]["train/plenoxel"]
    proc = recon_cli(
        "train",
        "-w",
        str(trained),
        "--method",
        "plenoxel",
        "--force",
        "--set",
        "resolutions=24,48",
        "--set",
        "no_such_option=1",
        check=False,
    )
    assert proc.returncode != 0 and "no_such_option" in proc.stderr
    assert (trained / "runs" / "plenoxel" / "model.pt").read_bytes() == before
    assert (
        json.loads((trained / "workspace.json").read_text())["stages"]["train/plenoxel"] == record
    )
    assert sorted(p.name for p in (trained / "runs").iterdir()) == sorted(
        p.name for p in (trained / "runs").iterdir() if not p.name.startswith(".")
    )


def train_3dgs(ws, run, steps, *extra):
    """`recon train --method 3dgs` of `steps` steps into run `run`, one evaluation view."""
    recon_cli(
        "train", "-w", str(ws), "--method", "3dgs", "--run", run, "--steps", steps,
        "--eval-views", "1", *extra,
    )  # fmt: skip


def test_3dgs_train_render_and_splat_export(trained):
    from recon.gaussians.ply import read_splat_ply
    from recon.gaussians.splat_formats import read_compressed_ply, read_dot_splat

    recon_cli(
        "train",
        "-w",
        str(trained),
        "--method",
        "3dgs",
        "--steps",
        "30",
        "--eval-views",
        "1",
        "--set",
        "init_points=500",
    )
    recon_cli("render", "-w", str(trained), "--run", "3dgs")
    out = json.loads(recon_cli("export", "-w", str(trained), "--run", "3dgs", "--json").stdout)
    ply = read_splat_ply(out["path"])
    means = ply["means"]
    assert len(means) == out["gaussians"] > 0
    # exported in the original units: the sphere (radius 0.5 at the origin) lies inside a ~1.5 m box
    assert np.abs(means).max() < 3.0
    proc = recon_cli("export", "-w", str(trained), "--run", "plenoxel", check=False)
    assert proc.returncode != 0 and "3dgs" in proc.stderr
    # the compact formats: the same Gaussians, read back as the viewers decode them
    G = out["gaussians"]
    for fmt, reader, size in (
        ("splat", read_dot_splat, 32 * G),
        ("compressed-ply", read_compressed_ply, None),
    ):
        args = ("export", "-w", str(trained), "--run", "3dgs", "--format", fmt, "--json")
        done = json.loads(recon_cli(*args, "--sh-degree", "0").stdout)
        back = reader(done["path"])
        assert len(back["means"]) == G and done["sh_degree"] == 0
        assert np.allclose(np.sort(back["means"][:, 0]), np.sort(means[:, 0]), atol=0.02)
        if size is not None:
            assert done["bytes"] == size
    assert out["antialias_baked"] is False
    # an antialiased run exports its opacities times their mean compensation over the
    # training views (viewers do not compensate): never above the model's own, some below
    train_3dgs(trained, "aa", "10", "--set", "init_points=500", "--set", "antialiased=true")
    aa = json.loads(recon_cli("export", "-w", str(trained), "--run", "aa", "--json").stdout)
    assert aa["antialias_baked"] is True
    from recon.workspace import Workspace
    from recon.workspace.runs import load_run

    model = load_run(Workspace(trained), "aa")[0]
    raw = model.params["opacity_logits"].detach().double().sigmoid().numpy().reshape(-1)
    baked = 1 / (1 + np.exp(-read_splat_ply(aa["path"])["opacity_logits"].astype(np.float64)))
    assert baked.shape == raw.shape
    assert (baked <= raw + 1e-6).all() and (baked < raw - 1e-3).any()
    bad = recon_cli("export", "-w", str(trained), "--run", "3dgs", "--sh-degree", "4", check=False)
    assert bad.returncode == 2 and "sh-degree" in bad.stderr
    # the exported file seeds a new run through the CLI flag (round trip of the PLY format)
    train_3dgs(trained, "from-ply", "1", "--init-from-ply", out["path"])
    run = json.loads((trained / "runs" / "from-ply" / "run.json").read_text())
    assert run["config"]["init_ply"] == str(Path(out["path"]).resolve())
    assert (
        json.loads(recon_cli("export", "-w", str(trained), "--run", "from-ply", "--json").stdout)[
            "gaussians"
        ]
        == out["gaussians"]
    )  # one step densifies nothing
    proc = recon_cli(
        "train",
        "-w",
        str(trained),
        "--method",
        "plenoxel",
        "--run",
        "x",
        "--init-from-ply",
        out["path"],
        check=False,
    )
    assert proc.returncode != 0 and "3dgs" in proc.stderr
