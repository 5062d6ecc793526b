"""Ctrl-C and kill -9 during `recon train`: nothing half-written, and --resume continues to the
same model an uninterrupted run reaches (same seed, same steps)."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from tests.conftest import REPO, recon_cli, sphere_workspace

# long enough that a signal sent once a checkpoint past step 5 is seen arrives well before the
# run ends (a run that finished first would test nothing)
TRAIN = [
    "--method",
    "plenoxel",
    "--steps",
    "240",
    "--eval-views",
    "1",
    "--eval-every",
    "1000",
    "--checkpoint-every",
    "0.5",
    "--set",
    "resolutions=16,32",
    "--set",
    "upsample_steps=30",
    "--set",
    "rays_per_batch=1024",
    "--set",
    "occupancy_res=16",
    "--set",
    "samples_per_batch=32768",
    "--threads",
    "1",
]


@pytest.fixture(scope="module")
def ws(tmp_path_factory):
    ws = sphere_workspace(tmp_path_factory.mktemp("interrupt"))
    recon_cli("train", "-w", str(ws), "--run", "straight", *TRAIN)
    return ws


def _start(ws, run):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen(
        [sys.executable, "-m", "recon.cli", "train", "-w", str(ws), "--run", run, *TRAIN],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=REPO,
    )


def _wait_for_checkpoint(ws, run, timeout=120, count=1):
    """Until `count` checkpoints past step 5 are listed."""
    index = ws / "runs" / run / "checkpoints" / "index.json"
    t0 = time.time()
    while time.time() - t0 < timeout:
        if index.exists() and sum(e["step"] > 5 for e in json.loads(index.read_text())) >= count:
            return
        time.sleep(0.02)
    raise AssertionError("no checkpoint appeared")


def _same_model(ws, a, b):
    sa = torch.load(ws / "runs" / a / "model.pt", weights_only=True)["state_dict"]
    sb = torch.load(ws / "runs" / b / "model.pt", weights_only=True)["state_dict"]
    assert sa.keys() == sb.keys()
    for k in sa:
        assert torch.equal(sa[k], sb[k]), k


def test_sigint_saves_checkpoint_and_resume_matches_uninterrupted(ws):
    proc = _start(ws, "ctrl_c")
    _wait_for_checkpoint(ws, "ctrl_c")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "--resume" in err, err  # 0: it ended before the signal
    assert json.loads((ws / "runs" / "ctrl_c" / "run.json").read_text())["status"] == "interrupted"
    recon_cli("train", "-w", str(ws), "--run", "ctrl_c", "--resume", *TRAIN)
    _same_model(ws, "straight", "ctrl_c")


def test_sigkill_then_resume_matches_uninterrupted(ws):
    proc = _start(ws, "killed")
    _wait_for_checkpoint(ws, "killed")
    proc.kill()
    proc.wait(30)
    ck_dir = ws / "runs" / "killed" / "checkpoints"
    assert not [
        p for p in ck_dir.iterdir() if ".tmp-" in p.name
    ]  # nothing half-written is left visible
    recon_cli("train", "-w", str(ws), "--run", "killed", "--resume", *TRAIN)
    _same_model(ws, "straight", "killed")


def test_corrupt_checkpoint_falls_back_to_the_previous_one(ws):
    proc = _start(ws, "corrupt")
    _wait_for_checkpoint(ws, "corrupt", count=2)  # one to corrupt, one to fall back to
    proc.kill()
    proc.wait(30)
    ck_dir = ws / "runs" / "corrupt" / "checkpoints"
    index = json.loads((ck_dir / "index.json").read_text())
    assert len(index) >= 2
    (ck_dir / index[-1]["file"]).write_bytes(b"garbage")
    out = recon_cli("train", "-w", str(ws), "--run", "corrupt", "--resume", *TRAIN)
    assert "corrupt" in out.stderr
    _same_model(ws, "straight", "corrupt")
