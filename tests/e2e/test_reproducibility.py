"""Same scene, method, seed and thread count -> the same model and the same metrics, run to run
(issue "reproducible pipelines"). Two CPU threads, so the numba kernels' parallel reductions are
exercised: they split work statically and reduce per-thread buffers in a fixed order."""

import json

import pytest
import torch

from tests.conftest import recon_cli, sphere_workspace

METHODS = {
    "plenoxel": [
        "--set",
        "resolutions=16,32",
        "--set",
        "upsample_steps=6",
        "--set",
        "occupancy_res=16",
    ],
    "ngp": ["--set", "rays_per_batch=512"],
    "nerf": ["--set", "rays_per_batch=256"],
    "3dgs": ["--set", "init_points=300"],
    "sdf": [
        "--set",
        "rays_per_batch=256",
        "--set",
        "log2_table_size=14",
        "--set",
        "eikonal_points=256",
        "--set",
        "occupancy_res=16",
    ],
}


@pytest.fixture(scope="module")
def ws(tmp_path_factory):
    return sphere_workspace(tmp_path_factory.mktemp("repro"), n_test=2)


def _train_and_eval(ws, method: str, run: str) -> dict:
    recon_cli(
        "train",
        "-w",
        str(ws),
        "--method",
        method,
        "--run",
        run,
        "--steps",
        "12",
        "--seed",
        "3",
        "--threads",
        "2",
        "--eval-views",
        "0",  # compared below through `recon eval`
        *METHODS[method],
        env={"OMP_NUM_THREADS": "2", "NUMBA_NUM_THREADS": "2"},
    )
    # the evaluation runs in this process (one thread): the same for both runs
    return json.loads(
        recon_cli(
            "eval", "-w", str(ws), "--run", run, "--json", "--no-lpips", "--no-pictures"
        ).stdout
    )[run]


@pytest.mark.parametrize("method", sorted(METHODS))
def test_same_seed_and_threads_give_identical_model_and_metrics(ws, method):
    a = _train_and_eval(ws, method, f"{method}-a")
    b = _train_and_eval(ws, method, f"{method}-b")
    assert a["per_view"].keys() == b["per_view"].keys()
    for stem in a["per_view"]:
        assert a["per_view"][stem]["psnr"] == pytest.approx(
            b["per_view"][stem]["psnr"], abs=1e-6
        ), stem
    sa = torch.load(ws / "runs" / f"{method}-a" / "model.pt", weights_only=True)["state_dict"]
    sb = torch.load(ws / "runs" / f"{method}-b" / "model.pt", weights_only=True)["state_dict"]
    assert sa.keys() == sb.keys()
    for k in sa:
        assert torch.equal(sa[k], sb[k]), k
    versions = json.loads((ws / "workspace.json").read_text())["stages"][f"train/{method}-a"][
        "versions"
    ]
    assert versions["threads"] == 2 and "torch" in versions and "recon" in versions
