"""3D Gaussian splatting on CUDA through gsplat (Ye et al. 2024, "gsplat: An Open-Source
Library for Gaussian Splatting"): its fused EWA projection, tile intersection and tile
rasterizer (forward and backward in CUDA, memory linear in the tile intersections), with
recon's conventions mapped onto gsplat's. The numba kernels stay the CPU path.

The conventions, each checked against gsplat's pure-torch reference (`gsplat.cuda._torch_impl`)
and recon's own rasterizer by tests/gaussians/test_gsplat_glue.py:
- view matrix: gsplat's `viewmats` are world-to-camera 4x4 in OpenCV axes (x right, y down,
  z forward), i.e. recon's `cam_from_world`;
- intrinsics: the same K; both put pixel centres at +0.5 (means2d = K x / z, pixel (i, j)
  sampled at (i + 0.5, j + 0.5));
- quaternions (w, x, y, z), normalised on use, in both; scales = exp(log_scales); opacities =
  sigmoid(opacity_logits), times the antialiasing compensation when antialiased (recon computes
  it from the conics: the same sqrt(det Sigma / det Sigma') as gsplat's `compensations`);
- the 0.3 px^2 dilation (`projection.DILATION`, gsplat's `eps2d`) and the 1.3x guard band of
  the Jacobian are the same; so is the near plane (depth > near);
- SH colours: gsplat's fused kernel evaluates the same real SH basis, in the same order and
  signs (the 3DGS reference's), of the unit direction from the camera centre to the mean, with
  its gradient reaching the means through that direction; recon adds the reference's 0.5 offset
  and clamp (`projection.sh_colors`) and hands the colours over as features. One kernel each
  way where the torch evaluation of degree 3 takes ~200 small ones a step;
- radii: gsplat's are per axis, ceil(3.33 sqrt(Sigma'_xx)), ceil(3.33 sqrt(Sigma'_yy)) (3.33 =
  sqrt(2 ln 255): every pixel where alpha can reach 1/255), recon's one 3-sigma radius of the
  larger eigenvalue; recon's densification reads the larger of the two axes.
- compositing: the same front-to-back sum, alpha >= 1/255 and the stop before T < 1e-4;
  gsplat clamps alpha at 0.999 where recon's CPU kernels clamp at 0.99 (`alpha.ALPHA_MAX`).

gsplat's non-packed mode is used: a step renders one camera, and its dense (G,) outputs (about
40 bytes a Gaussian) are what recon's per-Gaussian densification statistics index anyway; the
packed mode saves memory only when many cameras see a small part of the scene each.
"""

from __future__ import annotations

import importlib.util
from types import SimpleNamespace

import torch
from torch import Tensor

from recon.gaussians.projection import DILATION

TILE = 16  # gsplat's tile side (its kernels are tuned for 16 x 16 thread blocks)


def cuda_missing() -> str | None:
    """What 3dgs lacks on a CUDA device: gsplat, if it is not installed (None if it is)."""
    if importlib.util.find_spec("gsplat") is None:
        return "gsplat (pip install 'recon[cuda]')"
    return None


def _gsplat_ops() -> SimpleNamespace:
    """gsplat's CUDA entry points (imported on first use: the package compiles its CUDA code
    with the machine's nvcc the first time a kernel runs)."""
    try:
        from gsplat.cuda._wrapper import (
            fully_fused_projection,
            isect_offset_encode,
            isect_tiles,
            rasterize_to_pixels,
            spherical_harmonics,
        )
    except ImportError as e:
        raise RuntimeError(
            "3dgs on a CUDA device needs gsplat: pip install 'recon[cuda]' (or pass "
            f"--device cpu) [{e}]"
        ) from None
    return SimpleNamespace(
        project=fully_fused_projection,
        isect_tiles=isect_tiles,
        isect_offset_encode=isect_offset_encode,
        rasterize=rasterize_to_pixels,
        sh=spherical_harmonics,
    )


# The entry points in use; tests swap in gsplat's pure-torch twins to run the glue on a CPU.
OPS: SimpleNamespace | None = None


def ops() -> SimpleNamespace:
    global OPS
    if OPS is None:
        OPS = _gsplat_ops()
    return OPS


def uses_gsplat(t: Tensor) -> bool:
    """Whether splats on `t`'s device go through gsplat: CUDA tensors do."""
    return t.device.type == "cuda"


def project(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    K: Tensor,
    cam_from_world: Tensor,
    width: int,
    height: int,
    near: float = 0.01,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """EWA projection of G Gaussians into one camera by gsplat (`projection.project_gaussians`'
    contract): means (G, 3), quats (G, 4) (w, x, y, z), log_scales (G, 3), K (3, 3),
    cam_from_world (4, 4) -> means2d (G, 2) px, conics (G, 3), depths (G,) camera z,
    radii (G, 2) int32 per-axis half sides in px (0 = culled). Differentiable in means, quats
    and log_scales."""
    radii, means2d, depths, conics, _ = ops().project(
        means,
        None,
        quats,
        torch.exp(log_scales),
        cam_from_world[None].to(means),
        K[None].to(means),
        width,
        height,
        eps2d=DILATION,
        near_plane=near,
        packed=False,
    )
    return means2d[0], conics[0], depths[0], radii[0]


def sh_colors(
    means: Tensor, sh_dc: Tensor, sh_rest: Tensor, degree: int, center: Tensor, visible: Tensor
) -> Tensor:
    """c = max(SH_degree(sh, d) + 0.5, 0), d = (mu - o) / |mu - o|, by gsplat's SH kernel
    (`projection.sh_colors`' values and gradients): means (G, 3), sh_dc (G, 1, 3), sh_rest
    (G, K - 1, 3) with K >= (degree + 1)^2, center (3,) the camera's, visible (G,) bool (the
    others are skipped: 0.5, the offset alone, and no gradient) -> (G, 3)."""
    coeffs = torch.cat([sh_dc, sh_rest], 1) if degree > 0 else sh_dc
    colors = ops().sh(degree, means - center, coeffs, visible)
    # gsplat leaves the skipped rows as allocated (uninitialised): zero them, so that no stray
    # value (a NaN, say) ever reaches a reduction over all splats
    colors = torch.where(visible[:, None], colors, 0.0)
    return torch.clamp_min(colors + 0.5, 0.0)


def tile_grid(width: int, height: int) -> tuple[int, int]:
    """(tiles_x, tiles_y) of gsplat's 16 px tiles."""
    return (width + TILE - 1) // TILE, (height + TILE - 1) // TILE


def intersections(
    means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int
) -> tuple[Tensor, Tensor]:
    """gsplat's (tile, depth)-sorted splat lists: offsets (tiles_y, tiles_x) int32, the start of
    each tile's list in flatten_ids (n_isects,) int32, which holds splat indices."""
    tiles_x, tiles_y = tile_grid(width, height)
    _, isect_ids, flatten_ids = ops().isect_tiles(
        means2d[None].detach(), radii[None], depths[None].detach(), TILE, tiles_x, tiles_y
    )
    offsets = ops().isect_offset_encode(isect_ids, 1, tiles_x, tiles_y)
    return offsets[0], flatten_ids


def rasterize(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    radii: Tensor,
    depths: Tensor,
    width: int,
    height: int,
    abs_grad: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """F(p) = sum_i T_i alpha_i f_i and T_final(p) by gsplat's tile rasterizer
    (`rasterize.rasterize_features`' contract): means2d (G, 2), conics (G, 3), opacities (G,),
    features (G, D), radii (G, 2) per axis, depths (G,) -> image (H, W, D), T (H, W).
    `abs_grad` (G, 2), if given, receives sum_p |dL_p / d mu'| in the backward (gsplat's
    `absgrad`; Ye et al. 2024, "AbsGS", Sec. 4.2)."""
    offsets, flatten_ids = intersections(means2d, radii, depths, width, height)
    batched = means2d[None].contiguous()
    if abs_grad is not None and batched.requires_grad:
        # gsplat's backward leaves the per-pixel absolute sums on the tensor it was given, as
        # `.absgrad`, before autograd hands that tensor's gradient on (this hook)
        def add_abs_grad(grad: Tensor) -> None:
            abs_grad.add_(batched.absgrad[0].to(abs_grad))

        batched.register_hook(add_abs_grad)
    image, alpha = ops().rasterize(
        batched,
        conics[None],
        features[None].contiguous(),
        opacities[None].contiguous(),
        width,
        height,
        TILE,
        offsets[None],
        flatten_ids,
        absgrad=abs_grad is not None,
    )
    return image[0], 1 - alpha[0, ..., 0]
