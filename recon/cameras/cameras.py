"""A batch of pinhole cameras: intrinsics, `cam_from_world` extrinsics and image sizes."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


def intrinsics_matrix(fx: Tensor, fy: Tensor, cx: Tensor, cy: Tensor) -> Tensor:
    """K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] for (C,) parameters -> (C, 3, 3)."""
    K = torch.zeros(fx.shape + (3, 3), dtype=fx.dtype, device=fx.device)
    K[..., 0, 0], K[..., 1, 1] = fx, fy
    K[..., 0, 2], K[..., 1, 2] = cx, cy
    K[..., 2, 2] = 1.0
    return K


def invert_rigid(a_from_b: Tensor) -> Tensor:
    """Inverse of rigid (..., 4, 4) transforms: b_from_a = [R^T, -R^T t]."""
    R, t = a_from_b[..., :3, :3], a_from_b[..., :3, 3:]
    out = torch.zeros_like(a_from_b)
    out[..., :3, :3] = R.transpose(-1, -2)
    out[..., :3, 3:] = -R.transpose(-1, -2) @ t
    out[..., 3, 3] = 1.0
    return out


@dataclass
class Cameras:
    """C pinhole cameras (images are undistorted once in `sfm`, so training sees pinholes).

    K: (C, 3, 3) intrinsics in pixels, principal point in the pixel-edge convention
       (pixel (0, 0) covers [0, 1) x [0, 1), its centre is (0.5, 0.5)).
    cam_from_world: (C, 4, 4) rigid transforms, OpenCV camera frame.
    width, height: (C,) int64 image sizes in pixels.
    """

    K: Tensor
    cam_from_world: Tensor
    width: Tensor
    height: Tensor

    def __len__(self) -> int:
        return self.K.shape[0]

    def __getitem__(self, index) -> Cameras:
        if isinstance(index, int):
            index = slice(index, index + 1)
        return Cameras(self.K[index], self.cam_from_world[index], self.width[index], self.height[index])

    @property
    def world_from_cam(self) -> Tensor:
        return invert_rigid(self.cam_from_world)

    @property
    def centers(self) -> Tensor:
        """(C, 3) camera centres in the world frame."""
        return self.world_from_cam[:, :3, 3]

    @property
    def device(self) -> torch.device:
        return self.K.device

    def to(self, device=None, dtype=None) -> Cameras:
        return Cameras(
            self.K.to(device=device, dtype=dtype),
            self.cam_from_world.to(device=device, dtype=dtype),
            self.width.to(device=device),
            self.height.to(device=device),
        )

    def scaled(self, factor: float) -> Cameras:
        """Cameras for images resized by `factor` (0.5 = half size); pixel edges scale exactly."""
        K = self.K.clone()
        K[:, :2, :] *= factor
        w = torch.round(self.width.double() * factor).long()
        h = torch.round(self.height.double() * factor).long()
        return Cameras(K, self.cam_from_world.clone(), w, h)
