"""`recon train --device`: which device auto chooses and why (the log and run.json), the
preset and the throughput probe that follow from it, and --device cuda without CUDA refused
in one line with the workspace untouched."""

import json
import os

import pytest
import torch

from tests.conftest import recon_cli

IN_PROCESS = not os.environ.get("RECON_TEST_SUBPROCESS")


@pytest.fixture
def no_cuda(monkeypatch):
    """This process sees no CUDA device, wherever the test runs (in-process CLI calls only)."""
    if not IN_PROCESS and torch.cuda.is_available():
        pytest.skip("a subprocess would see this machine's CUDA device")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


def _files(ws):
    return {
        p.relative_to(ws): p.read_bytes()
        for p in ws.rglob("*")
        if p.is_file() and ".locks" not in p.parts
    }


def test_device_cuda_without_cuda_is_a_one_line_error(tmp_path, blender_dataset, no_cuda):
    ws = tmp_path / "ws"
    recon_cli("sfm", "--from-transforms", str(blender_dataset), "-w", str(ws))
    before = _files(ws)
    for budget in ([], ["--time-budget", "5"]):
        proc = recon_cli(
            "train", "-w", str(ws), "-m", "3dgs", "--device", "cuda", *budget, check=False
        )
        assert proc.returncode != 0
        lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
        assert len(lines) == 1 and "no CUDA device" in lines[0], proc.stderr
        assert "Traceback" not in proc.stderr
    assert _files(ws) == before and not (ws / "runs").exists()


def test_device_auto_says_why_and_a_budgeted_run_records_its_probe(
    tmp_path, blender_dataset, no_cuda, one_thread
):
    ws = tmp_path / "ws"
    recon_cli("sfm", "--from-transforms", str(blender_dataset), "-w", str(ws))
    proc = recon_cli(
        "train", "-w", str(ws), "-m", "3dgs", "--time-budget", "3", "--eval-views", "1"
    )
    assert "device cpu (auto: no CUDA device)" in proc.stderr
    assert "preset fast (auto: fast on a cpu device)" in proc.stderr
    assert "throughput probe" in proc.stderr and "k px/s" in proc.stderr
    doc = json.loads((ws / "runs" / "3dgs" / "run.json").read_text())
    assert (doc["device"], doc["device_reason"]) == ("cpu", "auto: no CUDA device")
    assert doc["preset"] == doc["train"]["preset"] == "fast"
    probe = doc["throughput"]["probe"]
    assert probe["levels"] == [1] and probe["samples"][0]["pixels"] == 16 * 16
    assert doc["throughput"]["source"] in ("prior", "measured") and doc["throughput"]["probe_s"] > 0
    assert doc["config"]["schedule_steps"] > 0  # planned from the budget
    # a --steps run measures nothing: no probe
    recon_cli("train", "-w", str(ws), "-m", "3dgs", "--run", "s", "--steps", "3")
    doc = json.loads((ws / "runs" / "s" / "run.json").read_text())
    assert doc["throughput"]["probe"] is None and doc["throughput"]["source"] == "prior"
