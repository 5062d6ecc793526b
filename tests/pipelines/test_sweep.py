"""The Snakemake sweep (pipelines/Snakefile): the DAG of a two-scene, two-method config, staleness
(touching one scene's photo reruns exactly that scene's jobs), the job specs a SLURM submission
carries (a fake sbatch on PATH records them), a tiny real run on sample_data end to end, and the
gathered table."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
SNAKEFILE = ROOT / "pipelines" / "Snakefile"
BIN = Path(sys.executable).parent
sys.path.insert(0, str(ROOT / "pipelines"))
import sweep
import sweep_table

pytestmark = pytest.mark.skipif(
    shutil.which("snakemake", path=str(BIN)) is None,
    reason="snakemake is not installed (pip install -e '.[pipelines]')",
)


def write_config(tmp: Path, scenes: dict, methods, budgets, **extra) -> Path:
    doc = {
        "base": str(tmp),
        "workspaces": "ws",
        "results": "results",
        "threads": 1,
        "methods": list(methods),
        "budgets": list(budgets),
        "scenes": scenes,
        **extra,
    }
    path = tmp / "sweep.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def snakemake(config: Path, *args, check=True, **kw) -> subprocess.CompletedProcess:
    cmd = [str(BIN / "snakemake"), "-s", str(SNAKEFILE), "--configfile", str(config)]
    cmd += ["--directory", str(config.parent), "--cores", "1", *args]
    out = subprocess.run(
        cmd,
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
        timeout=900,
        check=False,
        **kw,
    )
    if check and out.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed:\n{out.stdout}\n{out.stderr}")
    return out


def planned_outputs(config: Path) -> set[str]:
    """The outputs a dry run would make, relative to the results folder."""
    out = snakemake(config, "--dry-run")
    text = out.stdout + out.stderr
    results = config.parent / "results"
    found = set()
    for line in text.splitlines():
        m = re.match(r"\s+output:\s+(.*)", line)
        if m:
            for p in m.group(1).split(", "):
                found.add(str(Path(p.strip()).relative_to(results)))
    if "Nothing to be done" in text:
        assert not found
    return found


@pytest.fixture
def two_scenes(tmp_path):
    """Two copies of sample_data (transforms + images) as scenes a and b."""
    old = time.time() - 1000  # older than the outputs `made_by_hand` dates 100 s back: a
    # fresh clone's sample_data is only as old as the clone, which may be younger than that
    for name in ("a", "b"):
        shutil.copytree(ROOT / "sample_data", tmp_path / "data" / name)
        for path in (tmp_path / "data" / name).rglob("*"):
            os.utime(path, (old, old))
    scenes = {name: {"transforms": f"data/{name}"} for name in ("a", "b")}
    return tmp_path, scenes


def expected(scene: str, methods, budgets) -> set[str]:
    runs = [sweep.run_name(m, b) for m in methods for b in budgets]
    stages = ("train", "render", "mesh", "eval")
    return {f"{scene}/sfm.json"} | {f"{scene}/{s}/{r}.json" for s in stages for r in runs}


GATHERED = {"table.csv", "table.md", "a_speed_vs_error.png", "b_speed_vs_error.png"}


def made_by_hand(tmp: Path, outputs: set[str]) -> None:
    """Write every output (relative to the results folder) stage by stage, each stage a little
    newer than the one before, as if the whole sweep had run: a sweep that is up to date
    without running recon (Snakemake's --touch does not create missing files)."""
    order = ("sfm.json", "/train/", "/render/", "/mesh/", "/eval/", "")
    now = time.time() - 100
    for rank, key in enumerate(order):
        for rel in sorted(o for o in outputs if key in o):
            path = tmp / "results" / rel
            if not path.exists():
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text("{}")
                os.utime(path, (now + rank, now + rank))


def test_dag_of_two_scenes_and_two_methods(two_scenes):
    tmp, scenes = two_scenes
    config = write_config(tmp, scenes, ["3dgs", "ngp"], [30])
    planned = planned_outputs(config)
    assert (
        planned
        == expected("a", ["3dgs", "ngp"], [30]) | expected("b", ["3dgs", "ngp"], [30]) | GATHERED
    )


@pytest.mark.slow
def test_touching_a_photo_reruns_exactly_that_scenes_jobs(two_scenes):
    tmp, scenes = two_scenes
    config = write_config(tmp, scenes, ["3dgs", "plenoxel"], [30, 60])
    made_by_hand(tmp, planned_outputs(config))
    assert planned_outputs(config) == set()
    photo = sorted((tmp / "data" / "b" / "images").iterdir())[3]
    time.sleep(0.05)
    photo.touch()
    assert planned_outputs(config) == expected("b", ["3dgs", "plenoxel"], [30, 60]) | GATHERED


def test_bad_configs_are_refused_with_a_message(two_scenes):
    tmp, _ = two_scenes
    cases = [
        ({"x": {"photos": "data/a/images", "transforms": "data/a"}}, ["3dgs"], "exactly one"),
        ({"x": {"transforms": "data/a"}}, ["gaussians"], "unknown method"),
        ({"x": {"transforms": "data/missing"}}, ["3dgs"], "does not exist"),
    ]
    for scenes_doc, methods, message in cases:
        out = snakemake(write_config(tmp, scenes_doc, methods, [30]), "--dry-run", check=False)
        assert out.returncode != 0 and message in out.stdout + out.stderr, message


def slurm_submissions(tmp: Path, config: Path, expect: int) -> list[dict]:
    """Run the sweep with the SLURM executor against fake SLURM tools; return the sbatch calls
    once `expect` of them were made (the jobs never run: snakemake is stopped then)."""
    fake_bin = tmp / "fake-bin"
    fake_bin.mkdir(exist_ok=True)
    for tool in ("sbatch", "sacct", "squeue", "sinfo", "scontrol", "sacctmgr", "scancel"):
        target = fake_bin / tool
        target.write_text(f"#!{sys.executable}\n" + (ROOT / "tests" / "fake_slurm.py").read_text())
        target.chmod(0o755)
    log = tmp / "slurm-calls.jsonl"
    log.unlink(missing_ok=True)
    env = {**os.environ, "PATH": f"{fake_bin}:{os.environ['PATH']}", "FAKE_SLURM_LOG": str(log)}
    cmd = [str(BIN / "snakemake"), "-s", str(SNAKEFILE), "--configfile", str(config)]
    cmd += ["--directory", str(tmp), "--profile", str(ROOT / "pipelines/profiles/slurm")]
    cmd += ["--default-resources", "slurm_account=lab", "slurm_partition=short"]
    out_path = tmp / "snakemake-slurm.out"
    proc = subprocess.Popen(
        cmd,
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=out_path.open("w"),
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    calls: list[dict] = []
    try:
        deadline = time.time() + 120
        while time.time() < deadline and proc.poll() is None:
            if log.exists():
                lines = log.read_text().splitlines()
                calls = [json.loads(x) for x in lines if x.strip()]
                if sum(c["tool"] == "sbatch" for c in calls) >= expect:
                    break
            time.sleep(0.5)
    finally:  # the submitted jobs never run: stop snakemake and everything it started
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=60)
    out = out_path.read_text()
    sbatch = [c for c in calls if c["tool"] == "sbatch"]
    assert len(sbatch) == expect, out
    return sbatch


def sbatch_args(call: dict) -> dict:
    """sbatch's options from its argv (the plugin passes one shell string through `sh -c`,
    so argv is already split)."""
    argv, opts = call["argv"], {}
    i = 0
    while i < len(argv):
        a = argv[i]
        if a.startswith("--") and "=" in a:
            k, v = a.split("=", 1)
            opts[k] = v
        elif a.startswith("-") and i + 1 < len(argv) and not argv[i + 1].startswith("-"):
            opts[a] = argv[i + 1]
            i += 1
        else:
            opts[a] = True
        i += 1
    return opts


@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_slurm_jobs_carry_threads_memory_time_and_gpu(two_scenes, device):
    tmp, scenes = two_scenes
    config = write_config(tmp, scenes, ["3dgs", "ngp"], [120], device=device, threads=2)
    made_by_hand(tmp, planned_outputs(config))
    for stage in ("train", "render", "mesh", "eval"):  # scene a's runs are to be trained again
        shutil.rmtree(tmp / "results" / "a" / stage)
    for name in GATHERED:  # (intermediate files alone would not be remade for present targets)
        (tmp / "results" / name).unlink()
    calls = slurm_submissions(tmp, config, expect=2)
    photos = sweep.photo_count(sweep.scenes_from_config(yaml.safe_load(config.read_text()), tmp)[0])
    seen = set()
    for call in calls:
        opts = sbatch_args(call)
        wrapped = opts.get("--wrap", "") + call["stdin"]
        method = re.search(r"train:scene=a,method=(\w+),budget=120", wrapped).group(1)
        seen.add(method)
        assert opts["--comment"] == f"rule_train_wildcards_a_{method}_120"
        assert opts["-A"] == "lab" and opts["-p"] == "short"
        assert opts["--cpus-per-task"] == "2"
        # the scene's sfm record was only touched, so its workspace does not exist: the memory
        # asked is the bound for photos at the 1,600 px cap
        assert int(opts["--mem"]) == sweep.train_mem_mb(method, None, photos)
        assert int(opts["-t"]) == sweep.train_runtime_min(120)
        assert ("--gpus" in opts or "--gres" in opts) == (device == "cuda")
    assert seen == {"3dgs", "ngp"}


@pytest.mark.slow
def test_tiny_sweep_on_sample_data_end_to_end(tmp_path):
    shutil.copytree(ROOT / "sample_data", tmp_path / "data" / "sample")
    config = write_config(tmp_path, {"sample": {"transforms": "data/sample"}}, ["3dgs"], [15])
    snakemake(config)
    results = tmp_path / "results"
    rows = list(__import__("csv").DictReader((results / "table.csv").open()))  # one run: 3dgs-15s
    assert [(r["scene"], r["run"], r["method"]) for r in rows] == [("sample", "3dgs-15s", "3dgs")]
    row = rows[0]
    # it trained: a one-step model renders these views at ~10.9 dB; how far the budget gets
    # depends on the machine and its load (8 s: above 15 dB in earlier CI runs, 14.6 alone on
    # the 2-core VM, but 42 steps and 9.98 dB beside the other test worker, setup and the probe
    # taking most of it: hence 15 s), so the floor only tells a trained model from an untrained one
    assert float(row["psnr"]) > 12 and float(row["budget_s"]) == 15 and int(row["steps"]) > 1
    assert float(row["fscore"]) >= 0  # sample_data has a ground-truth mesh
    assert (results / "sample_speed_vs_error.png").stat().st_size > 1000
    assert "| sample | 3dgs-15s | 3dgs |" in (results / "table.md").read_text()
    # the workspace is recon's own: `recon status` reads it
    ws = tmp_path / "ws" / "sample"
    assert (ws / "runs" / "3dgs-15s" / "model.pt").exists()
    assert (ws / "runs" / "3dgs-15s" / "eval" / "metrics.json").exists()
    # nothing is stale afterwards
    assert planned_outputs(config) == set()


def test_table_rows_from_eval_documents(tmp_path):
    doc = {
        "ngp-60s": {
            "method": "ngp",
            "mean": {"psnr": 27.5, "ssim": 0.81, "lpips": 0.2, "psnr_border": 26.0},
            "geometry": {"status": "ok", "chamfer": 0.01, "fscore": 0.7},
            "speed": {"train_wall_s": 58.0, "time_budget_s": 60.0, "steps": 300},
            "render_ms_per_frame": 90.0,
        },
        "3dgs-60s": {
            "method": "3dgs",
            "mean": {"psnr": 30.0},
            "geometry": {"status": "no ground truth"},
            "speed": {"train_wall_s": 59.0, "trained_at": [100, 50]},
        },
    }
    p = tmp_path / "garden" / "eval" / "x.json"
    p.parent.mkdir(parents=True)
    p.write_text(json.dumps(doc))
    rows = sweep_table.gather([p])
    assert [r["run"] for r in rows] == ["3dgs-60s", "ngp-60s"]  # by method
    assert rows[0]["trained_at"] == "100x50" and rows[0]["chamfer"] is None
    assert rows[1]["fscore"] == 0.7 and rows[1]["scene"] == "garden"
    md = sweep_table.markdown(rows)
    assert "| garden | ngp-60s | ngp | 60.00 |" in md and md.count("\n| garden") == 2


def test_resources_follow_the_method_and_the_resolution():
    # 3dgs at 13.2 M training pixels measured 1,000 MB: 1.5 x (640 + 28 x 13.2) = 1,514 MB,
    # asked in whole 100s
    assert sweep.train_mem_mb("3dgs", 13_200_000, 67) == 1600
    assert sweep.train_mem_mb("ngp", 1_200_000, 67) > sweep.train_mem_mb("3dgs", 1_200_000, 67)
    assert sweep.train_mem_mb("3dgs", None, 10) > sweep.train_mem_mb("3dgs", 1_000_000, 10)
    assert sweep.train_runtime_min(600) == 21 and sweep.train_runtime_min(30) == 11
