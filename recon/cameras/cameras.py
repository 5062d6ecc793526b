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


def scale_intrinsics(K: Tensor, sx: Tensor | float, sy: Tensor | float) -> Tensor:
    """Intrinsics of an image resampled by (sx, sy) = (W'/W, H'/H) over the same field of view.

    With pixel edges at integers (pixel (0, 0) covers [0, 1)^2, its centre at 0.5), the image
    spans [0, W] x [0, H] and a resampling maps u' = sx u, v' = sy v, so K' = diag(sx, sy, 1) K:
    focal lengths AND principal point scale (with centres at integers instead, c' would be
    s (c + 0.5) - 0.5). K (..., 3, 3) -> (..., 3, 3).
    Example: fx = 1385.3, cx = 538 for W = 1076 resampled to W' = 269 -> fx' = 346.3, cx' = 134.5,
    still the centre of the new image.
    """
    out = K.clone()
    out[..., 0, :] = out[..., 0, :] * sx
    out[..., 1, :] = out[..., 1, :] * sy
    return out


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
        return Cameras(
            self.K[index], self.cam_from_world[index], self.width[index], self.height[index]
        )

    @property
    def world_from_cam(self) -> Tensor:
        return invert_rigid(self.cam_from_world)

    @property
    def centers(self) -> Tensor:
        """(C, 3) camera centres in the world frame: o_i = -sum_j R_ji t_j (-R^T t) of
        cam_from_world = [R | t], without the whole inverse (7 ops, not 24, in each 3dgs step)."""
        R, t = self.cam_from_world[:, :3, :3], self.cam_from_world[:, :3, 3:]
        return -(R * t).sum(-2)

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
        """Cameras for images resized by `factor` (0.5 = half size), sizes rounded."""
        w = torch.round(self.width.double() * factor).long().clamp_min(1)
        h = torch.round(self.height.double() * factor).long().clamp_min(1)
        return self.resized(w, h)

    def resized(self, width: Tensor | int, height: Tensor | int) -> Cameras:
        """The same views as images of `width` x `height` pixels (area-resampled over the same
        field of view): K scaled per axis by exactly W'/W and H'/H (`scale_intrinsics`)."""
        w = torch.as_tensor(width, device=self.width.device).expand_as(self.width).long()
        h = torch.as_tensor(height, device=self.height.device).expand_as(self.height).long()
        sx = (w.double() / self.width.double()).to(self.K)[:, None]
        sy = (h.double() / self.height.double()).to(self.K)[:, None]
        return Cameras(
            scale_intrinsics(self.K, sx, sy), self.cam_from_world.clone(), w.clone(), h.clone()
        )
