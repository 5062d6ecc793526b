"""pipelines/gpu_check.py (`make gpu-check`) where CI runs it, on a machine without a GPU: one
line and a non-zero exit; and its pure parts (the lego-400 subset, the log readers)."""

import json
import subprocess
import sys

import pytest
import torch

from tests.conftest import REPO, SHARED_DATA

sys.path.insert(0, str(REPO / "pipelines"))
import gpu_check


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")
def test_without_a_gpu_it_says_so_in_one_line():
    proc = subprocess.run(
        [sys.executable, "pipelines/gpu_check.py"],
        check=False,
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"gpu-check: no CUDA device (torch {torch.__version__} sees none)"
    ]
    assert not (REPO / ".gpu-site").exists()


def test_lego_subset_holds_every_eighth_test_view(tmp_path):
    lego = SHARED_DATA / "nerf_synthetic_lego_400"
    out = gpu_check.lego_subset(lego, tmp_path / "lego")
    test = json.loads((out / "transforms_test.json").read_text())["frames"]
    train = json.loads((out / "transforms_train.json").read_text())["frames"]
    assert len(test) == 25 and len(train) == 100
    assert [f["file_path"] for f in test[:3]] == ["./test/r_0", "./test/r_8", "./test/r_16"]
    assert (out / "test" / "r_8.png").exists()


def test_heldout_psnr_at_60_s_and_at_the_end(tmp_path):
    log = tmp_path / "log.jsonl"
    lines = [
        {"step": 1, "wall_s": 0.1, "loss": 0.3},
        {"step": 900, "wall_s": 30.2, "test_psnr": 25.0},
        {"step": 1800, "wall_s": 60.4, "test_psnr": 29.5},
        {"step": 3500, "wall_s": 118.0, "test_psnr": 31.25},
    ]
    log.write_text("".join(json.dumps(x) + "\n" for x in lines))
    psnrs = gpu_check.heldout_psnrs(log)
    assert gpu_check.psnr_at(psnrs, 60) == {"wall_s": 60.4, "psnr": 29.5}
    assert gpu_check.psnr_at(psnrs, psnrs[-1][0]) == {"wall_s": 118.0, "psnr": 31.25}
    assert gpu_check.psnr_at(psnrs, 200) is None


def test_profile_counts_a_steps_ops_on_a_cpu(tmp_path):
    """pipelines/gpu_profile.py (`gpu_check.py --profile`) on a CPU: the step's ops and their
    host times (no device activity there)."""
    from tests.conftest import sphere_workspace

    ws = sphere_workspace(tmp_path, n_train=4, size=24)
    out = tmp_path / "profile.json"
    proc = subprocess.run(
        [sys.executable, "pipelines/gpu_profile.py", "-w", str(ws), "--method", "ngp"]
        + ["--device", "cpu", "--warmup", "4", "--steps", "3", "--out", str(out)],
        check=False,
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(out.read_text())
    assert doc["method"] == "ngp" and doc["preset"] == "fast" and doc["image_size"] == [24, 24]
    assert doc["wall_ms_per_step"] > 0 and doc["aten_ops_per_step"] > 50
    assert doc["kernel_ms_per_step"] == 0 and doc["launches_per_step"] == 0
    assert (
        "aten::mm" in doc["top_ops_cpu_ms_per_step"]
        or "aten::addmm" in doc["top_ops_cpu_ms_per_step"]
    )


def test_importable_checks_every_module_in_one_child():
    assert gpu_check.importable(["json", "recon", "no_such_module_here"]) == {"json", "recon"}
    assert gpu_check.importable([]) == set()
