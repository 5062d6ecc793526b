"""The method registry: the list the CLI offers, capabilities instead of names, and files from
a newer recon refused with a clear error."""

import json

import pytest
import torch

from recon.models.registry import METHOD_NAMES, MODEL_SCHEMA_VERSION, import_methods, load_model
from recon.workspace import Workspace, WorkspaceError
from recon.workspace.runs import load_run


def test_every_listed_method_registers_and_declares_its_capabilities():
    from recon.models.nerf import NeRFModel
    from recon.models.ngp import NGPModel
    from recon.models.plenoxel import PlenoxelModel
    from recon.models.splatting import GaussianModel

    specs = import_methods()
    assert set(METHOD_NAMES) <= set(specs)  # tests may register toy methods of their own
    classes = {"nerf": NeRFModel, "ngp": NGPModel, "plenoxel": PlenoxelModel, "3dgs": GaussianModel}
    assert {n for n, c in classes.items() if c.has_density} == {"nerf", "ngp", "plenoxel"}
    assert {n for n, c in classes.items() if c.exports_splats} == {"3dgs"}
    assert {n for n, s in specs.items() if s.starts_from_splats} == {"3dgs"}


def test_a_model_file_from_a_newer_recon_is_refused(tmp_path):
    path = tmp_path / "model.pt"
    torch.save(
        {
            "schema_version": MODEL_SCHEMA_VERSION + 1,
            "method": "ngp",
            "config": {},
            "state_dict": {},
        },
        path,
    )
    with pytest.raises(ValueError, match="newer recon"):
        load_model(path, scene=None)


def test_a_run_from_a_newer_recon_is_refused(tmp_path):
    ws = Workspace.create(tmp_path / "ws")
    ws.run_dir("r").mkdir(parents=True)
    ws.run_json("r").write_text(json.dumps({"schema_version": 99, "method": "ngp"}))
    ws.model_path("r").write_bytes(b"")
    with pytest.raises(WorkspaceError, match="newer recon"):
        load_run(ws, "r")


def test_a_saved_config_with_a_removed_option_still_loads():
    """A run saved before an option was removed (3dgs's pose_snap_px, replaced by the pose
    probation) loads with that key dropped; tuples come back as tuples."""
    from recon.models.plenoxel import PlenoxelConfig
    from recon.models.registry import config_from_json
    from recon.models.splatting_config import GaussiansConfig

    saved = {"pose_refine": True, "pose_snap_px": 1.5, "pose_snap_start": -1}
    assert GaussiansConfig(**config_from_json(GaussiansConfig, saved)).pose_refine
    pleno = config_from_json(PlenoxelConfig, {"resolutions": [32, 64]})
    assert PlenoxelConfig(**pleno).resolutions == (32, 64)


def test_choose_device_says_why(monkeypatch):
    """auto takes CUDA when there is one and names it; --device cuda without one is an error
    (the CLI's one line: tests/cli/test_train_cmd_device.py)."""
    from recon.models.registry import choose_device, pick_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda i=0: "NVIDIA H200")
    assert choose_device("auto") == (torch.device("cuda"), "auto: CUDA available: NVIDIA H200")
    assert choose_device("cpu") == (torch.device("cpu"), "--device cpu")
    assert choose_device("cuda") == (torch.device("cuda"), "--device cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert choose_device("auto") == (torch.device("cpu"), "auto: no CUDA device")
    assert pick_device("auto") == torch.device("cpu")
    with pytest.raises(ValueError, match="no CUDA device is available"):
        choose_device("cuda")


def test_a_method_missing_its_cuda_package_trains_on_the_cpu_under_auto(monkeypatch):
    """3dgs without gsplat on a CUDA machine: auto takes the CPU and says why, --device cuda is
    a one-line error naming what to install; the other methods need nothing more."""
    import importlib.util

    from recon.gaussians import gsplat_glue
    from recon.models.registry import choose_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda i=0: "NVIDIA H200")
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "gsplat" else find_spec(name)
    )
    specs = import_methods()
    missing = specs["3dgs"].cuda_missing()
    assert missing == gsplat_glue.cuda_missing() and "recon[cuda]" in missing
    assert all(specs[m].cuda_missing is None for m in ("nerf", "ngp", "plenoxel", "sdf"))
    device, why = choose_device("auto", missing)
    assert device == torch.device("cpu") and "needs gsplat" in why
    with pytest.raises(ValueError, match="needs gsplat"):
        choose_device("cuda", missing)
    monkeypatch.setattr(importlib.util, "find_spec", find_spec)
    assert specs["3dgs"].cuda_missing() is None  # installed here (the test extra)
