"""One camera's view of a set of Gaussians: projection + SH colour + tile rasterization, giving
rgb over a background, expected z-depth and accumulated opacity.

`gaussians` is any mapping with the model's attribute tensors: means (G, 3), quats (G, 4),
log_scales (G, 3), opacity_logits (G,), sh_dc (G, 1, 3), sh_rest (G, R, 3) with
R >= (degree + 1)^2 - 1.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from recon.cameras import Cameras
from recon.gaussians import gsplat_glue
from recon.gaussians.project_fused import project_fused
from recon.gaussians.projection import antialias_compensation, project_gaussians, sh_colors
from recon.gaussians.rasterize import rasterize_features


@dataclass
class ProjectedSplats:
    """Gaussians in one camera. means2d (G, 2) px, conics (G, 3), depths (G,) camera z,
    radii (G,) (0 = culled), opacities (G,) in [0, 1], colors (G, 3); width, height in px.
    Projected by gsplat (CUDA), they also carry its per-axis radii (G, 2), which its
    rasterizer bins by (`gsplat_glue`)."""

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor
    opacities: Tensor
    colors: Tensor
    width: int
    height: int
    radii_xy: Tensor | None = None


def splat_opacities(opacity_logits: Tensor, conics: Tensor, antialiased: bool) -> Tensor:
    """sigmoid(logit) (G,), times `antialias_compensation(conics)` if antialiased."""
    opacities = torch.sigmoid(opacity_logits)
    return opacities * antialias_compensation(conics) if antialiased else opacities


def image_size(camera: Cameras) -> tuple[int, int]:
    """(W, H) of the single camera `camera`: its size tensors read on the host (on a GPU a
    wait for the device's queue, which a caller that knows the size avoids by passing `size`)."""
    return int(camera.width[0]), int(camera.height[0])


def project_splats(
    gaussians: Mapping[str, Tensor],
    camera: Cameras,
    sh_degree: int,
    near: float = 0.01,
    antialiased: bool = False,
    size: tuple[int, int] | None = None,
) -> ProjectedSplats:
    """Project G Gaussians into the single camera `camera` (len 1), colours from SH of
    `sh_degree` seen from its centre, opacity = sigmoid(logit) (`splat_opacities`). CPU
    tensors take the fused numba pass (`project_fused`), CUDA tensors gsplat's projection
    (`gsplat_glue`), other devices the pure-torch twin (`project_splats_torch`). `size`
    (W, H): the camera's image size when the caller knows it (else read from the camera)."""
    if gsplat_glue.uses_gsplat(gaussians["means"]):
        return project_splats_gsplat(gaussians, camera, sh_degree, near, antialiased, size)
    if gaussians["means"].device.type != "cpu":
        return project_splats_torch(gaussians, camera, sh_degree, near, antialiased, size)
    g, dtype = gaussians, gaussians["means"].dtype
    W, H = size or image_size(camera)
    means2d, conics, depths, radii, colors = project_fused(
        g["means"],
        g["quats"],
        g["log_scales"],
        g["sh_dc"],
        g["sh_rest"],
        sh_degree,
        camera.K[0].to(dtype),
        camera.cam_from_world[0].to(dtype),
        W,
        H,
        near,
    )
    opacities = splat_opacities(g["opacity_logits"], conics, antialiased)
    return ProjectedSplats(means2d, conics, depths, radii, opacities, colors, W, H)


@torch.no_grad()
def mean_compensation(gaussians: Mapping[str, Tensor], cameras: Cameras, near: float) -> Tensor:
    """(G,) each Gaussian's `antialias_compensation` averaged over the views of `cameras` that
    it projects into (radius > 0); 1 where none does. A viewer without the compensation (every
    INRIA-style renderer) shows an antialiased model's splats at their raw opacity, too opaque
    wherever they were sub-pixel in training; their opacity times this mean is the one opacity
    that matches the training views on average (what `recon export` writes for such a model)."""
    total = torch.zeros(len(gaussians["means"]), dtype=torch.float64)
    seen = torch.zeros_like(total)
    for view in range(len(cameras)):
        s = project_splats(gaussians, cameras[view], 0, near)
        visible = (s.radii > 0).cpu()
        total += torch.where(visible, antialias_compensation(s.conics).double().cpu(), 0.0)
        seen += visible.double()
    return torch.where(seen > 0, total / seen.clamp_min(1), 1.0)


def _colors(gaussians: Mapping[str, Tensor], camera: Cameras, sh_degree: int) -> Tensor:
    """(G, 3) SH colours of degree `sh_degree` seen from the camera's centre (torch)."""
    sh = gaussians["sh_dc"]
    if sh_degree > 0:
        sh = torch.cat([sh, gaussians["sh_rest"][:, : (sh_degree + 1) ** 2 - 1]], 1)
    center = camera.centers[0].to(gaussians["means"].dtype)
    return sh_colors(gaussians["means"], sh, sh_degree, center)


def project_splats_gsplat(
    gaussians: Mapping[str, Tensor],
    camera: Cameras,
    sh_degree: int,
    near: float = 0.01,
    antialiased: bool = False,
    size: tuple[int, int] | None = None,
) -> ProjectedSplats:
    """`project_splats` by gsplat's fused projection and SH kernels (CUDA)."""
    g, dtype = gaussians, gaussians["means"].dtype
    W, H = size or image_size(camera)
    means2d, conics, depths, radii_xy = gsplat_glue.project(
        g["means"],
        g["quats"],
        g["log_scales"],
        camera.K[0].to(dtype),
        camera.cam_from_world[0].to(dtype),
        W,
        H,
        near,
    )
    radii = radii_xy.amax(-1).to(dtype)
    opacities = splat_opacities(g["opacity_logits"], conics, antialiased)
    center = camera.centers[0].to(dtype)
    visible = (radii_xy > 0).all(-1)
    colors = gsplat_glue.sh_colors(g["means"], g["sh_dc"], g["sh_rest"], sh_degree, center, visible)
    return ProjectedSplats(means2d, conics, depths, radii, opacities, colors, W, H, radii_xy)


def project_splats_torch(
    gaussians: Mapping[str, Tensor],
    camera: Cameras,
    sh_degree: int,
    near: float = 0.01,
    antialiased: bool = False,
    size: tuple[int, int] | None = None,
) -> ProjectedSplats:
    """`project_splats` in vectorised torch with autograd (any device)."""
    dtype = gaussians["means"].dtype
    K, cam_from_world = camera.K[0].to(dtype), camera.cam_from_world[0].to(dtype)
    W, H = size or image_size(camera)
    means2d, conics, depths, radii = project_gaussians(
        gaussians["means"],
        gaussians["quats"],
        gaussians["log_scales"],
        K,
        cam_from_world,
        W,
        H,
        near,
    )
    colors = _colors(gaussians, camera, sh_degree)
    opacities = splat_opacities(gaussians["opacity_logits"], conics, antialiased)
    return ProjectedSplats(means2d, conics, depths, radii, opacities, colors, W, H)


def rasterize_splats(
    splats: ProjectedSplats, features: Tensor, abs_grad: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """F(p) = sum_i T_i alpha_i f_i (H, W, D) and T_final (H, W) of the projected splats with
    per-splat `features` (G, D), differentiable: gsplat's rasterizer for splats it projected,
    else `rasterize_features` (numba on the CPU). `abs_grad` (G, 2): see `rasterize_features`."""
    s = splats
    if s.radii_xy is not None:
        return gsplat_glue.rasterize(
            s.means2d,
            s.conics,
            s.opacities,
            features,
            s.radii_xy,
            s.depths,
            s.width,
            s.height,
            abs_grad,
        )
    return rasterize_features(
        s.means2d, s.conics, s.opacities, features, s.radii, s.depths, s.width, s.height, abs_grad
    )


def composite_rgb(
    splats: ProjectedSplats, background: Tensor, abs_grad: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """rgb = sum_i T_i alpha_i c_i + T_final bg -> rgb (H, W, 3), acc = 1 - T_final (H, W).
    `abs_grad` (G, 2): see `rasterize_features`."""
    image, T = rasterize_splats(splats, splats.colors, abs_grad)
    return image + T[..., None] * background.to(image), 1 - T


def composite_rgbd(splats: ProjectedSplats, background: Tensor) -> dict[str, Tensor]:
    """rgb (H, W, 3) over `background`, expected depth sum_i w_i z_i (H, W) (divide by acc for
    a surface depth), acc (H, W); w_i = T_i alpha_i. Depth rides along as a 4th channel."""
    s = splats
    features = torch.cat([s.colors, s.depths[:, None]], -1)
    image, T = rasterize_splats(s, features)
    rgb = image[..., :3] + T[..., None] * background.to(image)
    return {"rgb": rgb, "depth": image[..., 3], "acc": 1 - T}
