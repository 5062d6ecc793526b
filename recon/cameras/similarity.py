"""A similarity transform of 3D frames (scale, rotation, translation): the map from a capture's
world frame to the normalized scene frame the models train in, and back."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Similarity:
    """x_scene = scale * R @ x_world + t."""

    scale: float
    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,)

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * points @ self.R.T + self.t

    def invert_points(self, points_scene: np.ndarray) -> np.ndarray:
        """x_world = R^T (x_scene - t) / scale."""
        return ((points_scene - self.t) / self.scale) @ self.R

    def world_from_cam_to_scene(self, world_from_cam: np.ndarray) -> np.ndarray:
        """(C, 4, 4) world_from_cam -> scene_from_cam (rigid: the scale moves the centre only)."""
        out = world_from_cam.copy()
        out[:, :3, :3] = self.R @ world_from_cam[:, :3, :3]
        out[:, :3, 3] = self.apply(world_from_cam[:, :3, 3])
        return out

    def to_json(self) -> dict:
        return {"scale": float(self.scale), "R": self.R.tolist(), "t": self.t.tolist()}

    @staticmethod
    def from_json(d: dict) -> Similarity:
        return Similarity(float(d["scale"]), np.asarray(d["R"], float), np.asarray(d["t"], float))
