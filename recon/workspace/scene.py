"""Load the normalized scene written by `recon sfm` into tensors for the methods, at any level
of the workspace's image pyramid (`images_<K>/`: the sfm images area-downsampled by K, built
once on first use and shared by every run, eval and render)."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import torch

from recon.cameras.cameras import Cameras
from recon.cameras.similarity import Similarity
from recon.io.atomic import atomic_dir, atomic_write_json
from recon.io.images import read_image, resize_area, write_png
from recon.io.ply import read_points_ply
from recon.models.base import SceneInfo, TrainData
from recon.workspace.hashing import hash_file
from recon.workspace.workspace import Workspace, WorkspaceError

PYRAMID_MANIFEST = "pyramid.json"


def level_size(width: int, height: int, downscale: int) -> tuple[int, int]:
    """Image size at pyramid level `downscale`: (W // K, H // K), at least 1 pixel. The level
    covers the same field of view, so its intrinsics scale by exactly W'/W and H'/H
    (`Cameras.resized`). Example: 1076 x 1913 at K = 4 -> 269 x 478."""
    return max(1, width // downscale), max(1, height // downscale)


@dataclass
class Scene:
    """The contents of sfm/cameras.json, parsed."""

    frames: list[dict]
    scene_from_world: Similarity
    info: SceneInfo
    gt_mesh: str | None = None  # ground-truth mesh of the dataset (original units), if known

    def split(self, name: str) -> list[int]:
        return [i for i, f in enumerate(self.frames) if f["split"] == name]

    def cameras(self, indices: list[int], device="cpu", downscale: int = 1) -> Cameras:
        """The frames' cameras for images at pyramid level `downscale` (1: the sfm images)."""
        fr = [self.frames[i] for i in indices]
        K = torch.tensor(
            [[[f["fx"], 0, f["cx"]], [0, f["fy"], f["cy"]], [0, 0, 1]] for f in fr],
            dtype=torch.float64,
        )
        c = torch.tensor([f["cam_from_world"] for f in fr], dtype=torch.float64)
        w = torch.tensor([f["width"] for f in fr], dtype=torch.int64)
        h = torch.tensor([f["height"] for f in fr], dtype=torch.int64)
        cams = Cameras(K, c, w, h)
        if downscale != 1:
            sizes = [level_size(f["width"], f["height"], downscale) for f in fr]
            cams = cams.resized(
                torch.tensor([s[0] for s in sizes]), torch.tensor([s[1] for s in sizes])
            )
        return cams.to(device=device, dtype=torch.float32)

    def image_size(self, split: str = "train") -> tuple[int, int]:
        """(W, H) of the split's sfm images (the largest, should they differ)."""
        idx = self.split(split) or list(range(len(self.frames)))
        return (
            max(self.frames[i]["width"] for i in idx),
            max(self.frames[i]["height"] for i in idx),
        )

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
        near=float(doc["near"]),
        far=float(doc["far"]),
        points=points,
        point_colors=colors,
        scene_from_world=sim,
    )
    return Scene(doc["frames"], sim, info, doc.get("gt_mesh"))


def ensure_pyramid_level(ws: Workspace, scene: Scene, downscale: int) -> None:
    """Build `images_<K>/` (every frame's sfm image area-resampled to `level_size`) unless it
    exists for the current sfm output; a rerun of sfm makes the level stale and it is rebuilt.
    Built in a temporary folder and swapped in; concurrent builders wait for each other."""
    if downscale == 1:
        return
    if downscale < 1:
        raise WorkspaceError(f"downscale must be a positive integer, got {downscale}")
    level = ws.pyramid_dir(downscale)
    source = hash_file(ws.cameras_json)
    if _level_source(level) == source:
        return
    with ws.writer_lock(f"pyramid-{downscale}", wait=True):
        if _level_source(level) == source:  # built by another process while we waited
            return
        with atomic_dir(level) as tmp:
            for f in scene.frames:
                rel = ws.level_image(f["image"], downscale).relative_to(level)
                img = read_image(ws.resolve(f["image"]))  # RGB, or RGBA (alpha kept)
                write_png(
                    tmp / rel, resize_area(img, *level_size(f["width"], f["height"], downscale))
                )
            atomic_write_json(tmp / PYRAMID_MANIFEST, {"downscale": downscale, "source": source})


def _level_source(level) -> str | None:
    """The cameras.json hash a pyramid level was built from (None if absent or unreadable)."""
    try:
        return json.loads((level / PYRAMID_MANIFEST).read_text()).get("source")
    except (OSError, ValueError, AttributeError):
        return None


def load_images_and_alpha(
    ws: Workspace, scene: Scene, indices: list[int], downscale: int = 1
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The given frames (all of one size) at pyramid level `downscale` (built on first use),
    each file read once: (C, H, W, 3) float32 colour, and (C, H, W) float32 alpha, or None
    unless every one of them was written with alpha (`recon sfm` keeps an RGBA source's)."""
    ensure_pyramid_level(ws, scene, downscale)
    imgs = [read_image(ws.level_image(scene.frames[i]["image"], downscale)) for i in indices]
    shapes = {im.shape[:2] for im in imgs}
    if len(shapes) > 1:
        raise WorkspaceError(
            f"training images have different sizes {sorted(shapes)}; rerun sfm with one camera"
        )
    rgb = torch.from_numpy(np.stack([im[..., :3] for im in imgs]))
    if not all(im.shape[-1] == 4 for im in imgs):
        return rgb, None
    return rgb, torch.from_numpy(np.stack([im[..., 3] for im in imgs]))


def load_images(
    ws: Workspace, scene: Scene, indices: list[int], downscale: int = 1
) -> torch.Tensor:
    """(C, H, W, 3) float32 images of the given frames (`load_images_and_alpha`'s colour)."""
    return load_images_and_alpha(ws, scene, indices, downscale)[0]


def load_train_data(
    ws: Workspace, scene: Scene, split: str = "train", device="cpu", downscale: int = 1
) -> TrainData:
    idx = scene.split(split)
    if not idx:
        raise WorkspaceError(f"the scene has no '{split}' images")
    rgb, alpha = load_images_and_alpha(ws, scene, idx, downscale)
    return TrainData(
        rgb.to(device),
        scene.cameras(idx, device, downscale),
        None if alpha is None else alpha.to(device),
    )
