"""pipelines/Makefile: each target's commands, read from `make -n` (nothing runs)."""

import shutil
import subprocess

import pytest

from tests.conftest import REPO

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="no make on this machine")


def dry_run(tmp_path, *args) -> list[str]:
    out = subprocess.run(
        ["make", "-n", "-s", "-C", str(REPO / "pipelines"), f"WS={tmp_path / 'ws'}", *args],
        capture_output=True,
        text=True,
        check=True,
    )
    return [
        line.split("/bin/recon ", 1)[1] for line in out.stdout.splitlines() if "/bin/recon " in line
    ]


def test_mvs_target_runs_sfm_mvs_and_scores_the_mesh(tmp_path):
    ws = tmp_path / "ws"
    commands = dry_run(tmp_path, "SCENE=walnut", "mvs")
    assert [c.split()[0] for c in commands] == ["sfm", "mvs", "eval"]
    assert commands[1] == f"mvs -w {ws}"
    assert commands[2].startswith(f"eval -w {ws} --run mvs --gt-points ")
    assert commands[2].endswith("reference.ply")


def test_all_target_runs_every_stage_in_order(tmp_path):
    commands = dry_run(tmp_path, "SCENE=sample", "METHOD=3dgs", "BUDGET=30", "all")
    stages = [c.split()[0] for c in commands]
    assert stages[0] == "sfm" and stages[1] == "train" and "mvs" not in stages
    assert set(stages) == {"sfm", "train", "render", "mesh", "eval"}
    assert "--method 3dgs" in commands[1] and "--time-budget 30" in commands[1]
