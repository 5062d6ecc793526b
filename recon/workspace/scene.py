"""Load the normalized scene written by `recon sfm` into tensors for the methods."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import torch

from recon.cameras.cameras import Cameras
from recon.io.images import read_image
from recon.io.ply import read_points_ply
from recon.models.base import SceneInfo, TrainData
from recon.sfm.normalize import Similarity
from recon.workspace.workspace import Workspace, WorkspaceError


@dataclass
class Scene:
    """The contents of sfm/cameras.json, parsed."""

    frames: list[dict]
    scene_from_world: Similarity
    info: SceneInfo
    gt_mesh: str | None = None  # ground-truth mesh of the dataset (original units), if known

    def split(self, name: str) -> list[int]:
        return [i for i, f in enumerate(self.frames) if f["split"] == name]

    def cameras(self, indices: list[int], device="cpu") -> Cameras:
        fr = [self.frames[i] for i in indices]
        K = torch.tensor([[[f["fx"], 0, f["cx"]], [0, f["fy"], f["cy"]], [0, 0, 1]] for f in fr],
                         dtype=torch.float64)
        c = torch.tensor([f["cam_from_world"] for f in fr], dtype=torch.float64)
        w = torch.tensor([f["width"] for f in fr], dtype=torch.int64)
        h = torch.tensor([f["height"] for f in fr], dtype=torch.int64)
        return Cameras(K, c, w, h).to(device=device, dtype=torch.float32)

    def depth_to_world_units(self, depth: np.ndarray) -> np.ndarray:
        """z-depth in the normalized frame -> original (metric) units."""
        return depth / self.scene_from_world.scale


def load_scene(ws: Workspace, with_points: bool = True) -> Scene:
    if not ws.cameras_json.exists():
        raise WorkspaceError(f"{ws.root} has no sfm output: run `recon sfm` first")
    doc = json.loads(ws.cameras_json.read_text())
    sim = Similarity.from_json(doc["scene_from_world"])
    points = colors = None
    if with_points and ws.points_ply.exists():
        p, c = read_points_ply(ws.points_ply)
        points = torch.from_numpy(sim.apply(p.astype(np.float64)).astype(np.float32))
        colors = torch.from_numpy(c) if c is not None else None
    info = SceneInfo(
        aabb=torch.tensor(doc["aabb"], dtype=torch.float32),
        unbounded=bool(doc["unbounded"]),
        background=torch.tensor(doc["background"], dtype=torch.float32),
        near=float(doc["near"]), far=float(doc["far"]),
        points=points, point_colors=colors, scene_from_world=sim,
    )
    return Scene(doc["frames"], sim, info, doc.get("gt_mesh"))


def load_images(ws: Workspace, scene: Scene, indices: list[int]) -> torch.Tensor:
    """(C, H, W, 3) float32 images of the given frames (all of one size)."""
    imgs = [read_image(ws.resolve(scene.frames[i]["image"]))[..., :3] for i in indices]
    shapes = {im.shape for im in imgs}
    if len(shapes) > 1:
        raise WorkspaceError(f"training images have different sizes {sorted(shapes)}; rerun sfm with one camera")
    return torch.from_numpy(np.stack(imgs))


def load_train_data(ws: Workspace, scene: Scene, split: str = "train", device="cpu") -> TrainData:
    idx = scene.split(split)
    if not idx:
        raise WorkspaceError(f"the scene has no '{split}' images")
    return TrainData(load_images(ws, scene, idx).to(device), scene.cameras(idx, device))
