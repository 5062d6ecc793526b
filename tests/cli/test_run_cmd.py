"""`recon run` (recon/cli/run_cmd.py): the whole pipeline from photos, then nothing to redo."""

import json
import time

import pytest

from tests.conftest import SAMPLE_DATA, recon_cli


@pytest.mark.slow
def test_run_from_photos_to_the_report_then_skips_what_is_fresh(tmp_path):
    ws = tmp_path / "ws"
    args = ("run", str(SAMPLE_DATA / "images"), "-w", str(ws), "--time-budget", "15")
    first = recon_cli(*args, "--orbit-frames", "4", "--json", subprocess_=True)
    out = json.loads(first.stdout)
    assert [s["stage"] for s in out["stages"]] == [
        "sfm", "train/3dgs", "render/3dgs/test", "render/3dgs/orbit", "mesh/3dgs", "eval/3dgs",
    ]  # fmt: skip
    assert all(s["ran"] and s["exit_code"] == 0 for s in out["stages"])
    assert (ws / "report.html").exists() and out["report"] == str(ws / "report.html")
    assert (ws / "runs" / "3dgs" / "renders" / "orbit" / "video.mp4").exists()
    assert (
        json.loads((ws / "runs" / "3dgs" / "eval" / "metrics.json").read_text())["mean"]["psnr"]
        > 15
    )
    t0 = time.perf_counter()
    again = recon_cli(*args, "--orbit-frames", "4", subprocess_=True)
    assert again.returncode == 0 and f"report: {ws / 'report.html'}" in again.stdout
    assert again.stderr.count("is done and fresh: skipped") == 6
    assert time.perf_counter() - t0 < 60
    # another run on the same poses: sfm is reused, the new run's stages run
    second = recon_cli(
        "run", "-w", str(ws), "--run", "second", "--time-budget", "10", "--orbit-frames", "0",
        "--json", subprocess_=True,
    )  # fmt: skip
    stages = {s["stage"]: s["ran"] for s in json.loads(second.stdout)["stages"]}
    assert "sfm" not in stages and all(stages.values()) and "render/second/orbit" not in stages


def test_run_refuses_bad_input_in_one_line(tmp_path):
    missing = recon_cli("run", str(tmp_path / "nope"), "-w", str(tmp_path / "ws"), check=False)
    assert missing.returncode == 1 and "does not exist" in missing.stderr
    assert not (tmp_path / "ws").exists()
    bare = recon_cli("run", "-w", str(tmp_path / "ws"), check=False)
    assert bare.returncode == 2 and "give the PHOTOS or VIDEO" in bare.stderr
    bad = recon_cli(
        "run", str(SAMPLE_DATA / "images"), "-w", str(tmp_path / "ws"), "-m", "x", check=False
    )
    assert bad.returncode == 2 and not (tmp_path / "ws").exists()
