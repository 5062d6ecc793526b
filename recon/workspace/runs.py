"""A trained run read back from the workspace: its model rebuilt for the workspace's scene."""

from __future__ import annotations

import json

import torch

from recon.models.base import Model
from recon.models.registry import load_model
from recon.workspace.scene import Scene, load_scene
from recon.workspace.workspace import RUN_SCHEMA_VERSION, Workspace, WorkspaceError


def load_run(
    ws: Workspace, run: str, device: str | torch.device = "cpu"
) -> tuple[Model, Scene, dict]:
    """Rebuild a run's trained model -> (model in eval mode, scene, run.json)."""
    if not ws.run_json(run).exists():
        raise WorkspaceError(
            f"run '{run}' does not exist in {ws.root} (runs: {', '.join(ws.runs()) or 'none'})"
        )
    path = ws.model_path(run)
    if not path.exists():
        raise WorkspaceError(f"run '{run}' has no finished model yet (train it or resume it)")
    run_doc = json.loads(ws.run_json(run).read_text())
    if run_doc.get("schema_version", 1) > RUN_SCHEMA_VERSION:
        raise WorkspaceError(
            f"{ws.run_json(run)} was written by a newer recon (schema_version "
            f"{run_doc['schema_version']}): upgrade recon"
        )
    scene = load_scene(ws)
    return load_model(path, scene.info, device), scene, run_doc
