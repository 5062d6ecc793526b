"""Two `recon train` processes on one workspace : different run names both finish and
both are recorded in workspace.json; a second writer of the same run fails fast on the run lock
and leaves the first one's run alone. (The lock itself: tests/workspace/test_workspace.py.)"""

import json
import os
import subprocess
import sys
import time

import pytest

from tests.conftest import REPO
from tests.hard_cases.conftest import FAST_TRAIN, assert_one_line_error


def start_train(ws, run, steps, *extra):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "recon.cli",
            "train",
            "-w",
            str(ws),
            "--run",
            run,
            "--steps",
            str(steps),
            *FAST_TRAIN,
            *extra,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=REPO,
    )


@pytest.mark.slow
def test_two_runs_with_different_names_both_work(sphere_ws):
    procs = {run: start_train(sphere_ws, run, 5) for run in ("left", "right")}
    for run, proc in procs.items():
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err
        assert json.loads((sphere_ws / "runs" / run / "run.json").read_text())["status"] == "done"
    stages = json.loads((sphere_ws / "workspace.json").read_text())["stages"]
    assert {"train/left", "train/right"} <= set(stages)  # neither record overwrote the other


@pytest.mark.slow
def test_second_writer_of_the_same_run_fails_fast(sphere_ws):
    first = start_train(sphere_ws, "busy", 100_000)
    try:
        index = sphere_ws / "runs" / "busy" / "checkpoints" / "index.json"
        t0 = time.time()
        while not index.exists():  # the first checkpoint is written under the lock
            assert first.poll() is None, first.communicate()[1]
            assert time.time() - t0 < 120, "the first writer never started"
            time.sleep(0.2)
        second = start_train(sphere_ws, "busy", 5, "--resume")
        out, err = second.communicate(timeout=120)  # fails at the lock, never waits for the first
        assert_one_line_error(
            subprocess.CompletedProcess(second.args, second.returncode, out, err),
            "another recon process",
            "run-busy",
        )
        assert first.poll() is None  # the first writer is unharmed...
        assert (sphere_ws / "runs" / "busy" / "run.json").exists()  # ...and so is its run
    finally:
        first.kill()
        first.wait(30)
