"""`recon mvs` through the real CLI: the walnut ring (real photos, reference point cloud) at a
small size, and bad input that must leave the workspace as it was."""

import json

import numpy as np
import pytest
import trimesh

from recon.io.exr import read_depth_exr
from recon.metrics.geometry import geometry_metrics
from tests.conftest import SHARED_DATA, recon_cli

WALNUT = SHARED_DATA / "robovision_mvs_walnut"
REFERENCE = WALNUT / "reference_reconstructions" / "2016_10_24__17_43_02" / "reference.ply"


@pytest.mark.slow
@pytest.mark.skipif(not WALNUT.exists(), reason="../shared/data not present")
def test_mvs_on_the_walnut_ring_lands_on_the_reference_surface(tmp_path):
    ws = tmp_path / "ws"
    recon_cli(
        "sfm", "--from-transforms", str(WALNUT / "transforms.json"), "--downscale", "8",
        "-w", str(ws),
    )  # fmt: skip
    out = recon_cli("mvs", "-w", str(ws), "--planes", "96", "--previews", "1", "--json")
    result = json.loads(out.stdout)
    assert result["views"] == 10 and result["size"] == [160, 128]
    depths = sorted((ws / "mvs" / "depth").glob("*.exr"))
    assert len(depths) == 10  # training views only: held-out photos are never read
    d = read_depth_exr(depths[0])
    assert ((d == 0) | ((d > 0.12) & (d < 0.25))).all()  # metres: the ring's radius is ~0.18
    reference = np.asarray(trimesh.load(REFERENCE).vertices)
    mesh = trimesh.load(ws / "mvs" / "mesh.ply")
    m = geometry_metrics(mesh, reference, tau=0.0014, n_samples=30_000)
    # at 1/8 a pixel is ~0.4 mm on the walnut; the sphere of its mean radius scores 1.9 mm
    assert m["chamfer"] < 0.0012 and m["fscore"] > 0.6, m
    points = trimesh.load(ws / "mvs" / "points.ply")
    assert len(points.vertices) == result["points"] > 1000
    status = recon_cli("status", "-w", str(ws)).stdout
    assert "mvs" in status
    ev = recon_cli("eval", "-w", str(ws), "--run", "mvs", "--gt-points", str(REFERENCE), "--json")
    geo = json.loads(ev.stdout)["mvs"]["geometry"]
    assert geo["status"] == "ok" and geo["chamfer"] < 0.0012
    assert (ws / "mvs" / "metrics.json").exists()
    # the reports list it beside the runs: a geometry-only row, and its mesh and preview
    report = (ws / "report.md").read_text()
    assert "| mvs | mvs | 160×128 |" in report and "`recon mvs`" in report
    page = (ws / "report.html").read_text()
    assert 'id="run-mvs"' in page and 'href="mvs/mesh.ply"' in page
    assert 'src="mvs/preview_0.png"' in page
    # an sdf run asked to fits the fused points, and depends on the mvs stage from then on
    train = recon_cli(
        "train", "-w", str(ws), "--method", "sdf", "--steps", "2", "--eval-every", "1e6",
        "--surface-points", "on",
    )  # fmt: skip
    assert f"fitting {result['points']} surface points" in train.stdout + train.stderr
    record = json.loads((ws / "workspace.json").read_text())["stages"]["train/sdf"]
    assert record["upstream"] == ["sfm", "mvs"]


def test_mvs_refuses_bad_input_and_leaves_the_workspace_alone(tmp_path):
    proc = recon_cli("mvs", "-w", str(tmp_path / "nothing"), check=False)
    assert proc.returncode != 0 and len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "nothing").exists()

    ws = tmp_path / "ws"
    ws.mkdir()
    (ws / "workspace.json").write_text(json.dumps({"schema_version": 1, "stages": {}}))
    before = sorted(p.name for p in ws.iterdir())
    proc = recon_cli("mvs", "-w", str(ws), check=False)
    assert proc.returncode != 0 and "sfm" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert sorted(p.name for p in ws.iterdir() if not p.name.startswith(".")) == [
        n for n in before if not n.startswith(".")
    ]
    proc = recon_cli("mvs", "-w", str(ws), "--window", "4", check=False)
    assert proc.returncode != 0 and len(proc.stderr.strip().splitlines()) == 1


def test_surface_points_without_mvs_is_a_one_line_error(tmp_path):
    from tests.conftest import sphere_workspace

    ws = sphere_workspace(tmp_path, n_train=3, size=16)
    proc = recon_cli(
        "train", "-w", str(ws), "--method", "sdf", "--steps", "1", "--surface-points", "on",
        check=False,
    )  # fmt: skip
    assert proc.returncode != 0 and "recon mvs" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not (ws / "runs" / "sdf").exists()


def test_surface_points_are_off_unless_asked():
    from recon.models.registry import import_methods
    from recon.train.config import TrainConfig
    from recon.train.stage import surface_points_source

    sdf, ngp = import_methods()["sdf"], import_methods()["ngp"]
    assert surface_points_source(None, TrainConfig(method="sdf"), sdf) is None  # not even read
    asked = TrainConfig(method="ngp", surface_points="on")
    assert surface_points_source(None, asked, ngp) is None  # ngp does not fit them
