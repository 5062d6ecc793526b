"""`recon train --method sdf` through the real CLI on sample_data (ground-truth mesh): a short
run's zero-level-set mesh beats the untrained field's sphere on F-score, carries the field's
normals, and `recon mesh` writes pictures of it."""

import json

import numpy as np
import pytest

from tests.conftest import REPO, recon_cli

pytestmark = pytest.mark.slow  # whole training runs through the CLI: make test-all

SMALL = [
    "--set",
    "log2_table_size=14",
    "--set",
    "n_max=256",
    "--set",
    "march_steps=256",
    "--set",
    "eikonal_points=512",
    "--set",
    "occupancy_res=32",
]


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    ws = tmp_path_factory.mktemp("sdf") / "ws"
    recon_cli("sfm", "--from-transforms", str(REPO / "sample_data"), "-w", str(ws))
    # no held-out PSNR while training: geometry is what this file tests
    for run, steps in (("sdf", "150"), ("sphere", "1")):
        recon_cli(
            "train", "-w", str(ws), "--method", "sdf", "--run", run, "--steps", steps,
            "--downscale", "2", "--eval-views", "0", *SMALL,
        )  # fmt: skip
    return ws


def mesh_and_fscore(ws, run: str, *extra: str) -> tuple[dict, dict]:
    mesh = json.loads(
        recon_cli(
            "mesh", "-w", str(ws), "--run", run, "--resolution", "96", "--json", *extra
        ).stdout
    )
    # geometry is what this test reads: one held-out view, no pictures (a young field renders
    # ~160 samples a ray, so the images cost most of an evaluation)
    ev = json.loads(
        recon_cli(
            "eval", "-w", str(ws), "--run", run, "--no-lpips", "--json", "--every", "1000",
            "--no-pictures",
        ).stdout
    )  # fmt: skip
    return mesh, ev[run]["geometry"]


def test_trained_field_beats_its_initial_sphere_and_writes_normals_and_a_preview(workspace):
    import trimesh

    _, sphere = mesh_and_fscore(workspace, "sphere")
    mesh, trained = mesh_and_fscore(workspace, "sdf")
    assert mesh["level"] == "sdf = 0" and mesh["faces"] > 500
    assert trained["status"] == "ok" and sphere["status"] == "ok"
    assert trained["fscore"] > sphere["fscore"] + 0.2, (trained, sphere)
    path = workspace / "runs" / "sdf" / "mesh" / "mesh.ply"
    assert b"property float nx" in path.read_bytes()[:2000]  # per-vertex normals in the file
    loaded = trimesh.load(path, process=False)
    # the field's normals agree with the faces' where the surface is smooth
    agree = (
        loaded.vertex_normals * trimesh.Trimesh(loaded.vertices, loaded.faces).vertex_normals
    ).sum(-1)
    assert np.median(agree) > 0.9
    previews = [workspace / "runs" / "sdf" / "mesh" / name for name in mesh["previews"]]
    assert len(previews) == 3 and all(p.stat().st_size > 1000 for p in previews)
