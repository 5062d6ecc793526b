"""3D Gaussians to 2D splats: quaternion -> rotation, Sigma = R S S^T R^T, EWA projection
Sigma' = J W Sigma W^T J^T + 0.3 I, the stable 2x2 conic, the 3-sigma radius and SH colour
(Kerbl et al. 2023, Sec. 4, eqs. 5-6; EWA splatting: Zwicker et al. 2001).

All functions are vectorised torch with autograd, device-agnostic; G = number of Gaussians.
"""

from __future__ import annotations

import torch
from torch import Tensor

from recon.fields.sh import eval_sh

# Low-pass dilation added to every projected covariance so splats never shrink below a pixel.
DILATION = 0.3
# Frustum guard band: x/z and y/z are clamped to 1.3x the half field of view before J is built,
# as the reference does, so Gaussians far outside the view do not get huge, skewed footprints.
GUARD_BAND = 1.3
# Quaternions shorter than this are treated as this long (a zero quaternion gives R = I).
QUAT_EPS = 1e-12


def antialias_compensation(conics: Tensor, dilation: float = DILATION) -> Tensor:
    """conics (G, 3) = (A, B, C) of Sigma' = Sigma + dilation I -> (G,) sqrt(det Sigma /
    det Sigma'), the opacity factor that keeps a dilated splat's integral that of the
    undilated one (the 2D filter's normalisation of Yu et al. 2024, "Mip-Splatting", eq. 12;
    gsplat's "antialiased" mode with the 0.3 dilation). det Sigma / det Sigma' =
    det(I - dilation conic) = 1 - dilation (A + C) + dilation^2 (A C - B^2), so no inverse is
    needed. Example: Sigma = diag(0.3, 1.2) -> Sigma' = diag(0.6, 1.5) -> sqrt(0.36 / 0.9) =
    0.63246. Splats far below a pixel fade instead of staying as bright as a pixel-sized one."""
    A, B, C = conics.unbind(-1)
    ratio = 1 - dilation * (A + C) + dilation * dilation * (A * C - B * B)
    return torch.sqrt(ratio.clamp(1e-12, 1.0))


def normalize_quats(quats: Tensor) -> Tensor:
    """q / max(|q|, eps).  (..., 4) -> (..., 4); a zero quaternion stays zero (-> R = I), no NaN."""
    sq = (quats * quats).sum(-1, keepdim=True)
    return quats * torch.rsqrt(sq.clamp_min(QUAT_EPS**2))


def rotation_from_quats(quats: Tensor) -> Tensor:
    """R(q) for q = (w, x, y, z), normalised on use.  (..., 4) -> (..., 3, 3).

    R = [[1-2(y^2+z^2), 2(xy-wz), 2(xz+wy)], [2(xy+wz), 1-2(x^2+z^2), 2(yz-wx)],
         [2(xz-wy), 2(yz+wx), 1-2(x^2+y^2)]];  q = (cos 15deg, 0, 0, sin 15deg) is 30deg about z.
    """
    w, x, y, z = normalize_quats(quats).unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    )
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def covariance_factor(quats: Tensor, log_scales: Tensor) -> Tensor:
    """M = R(q) diag(exp(log_scales)), so that Sigma = M M^T.  (G, 4), (G, 3) -> (G, 3, 3)."""
    return rotation_from_quats(quats) * torch.exp(log_scales)[..., None, :]


def covariance_3d(quats: Tensor, log_scales: Tensor) -> Tensor:
    """Sigma = R S S^T R^T = M M^T.  (G, 4), (G, 3) -> (G, 3, 3)."""
    M = covariance_factor(quats, log_scales)
    return (M[..., :, None, :] * M[..., None, :, :]).sum(-1)


def ewa_covariance_2d(
    points_in_cam: Tensor, factor_in_cam: Tensor, K: Tensor, width: int, height: int
) -> Tensor:
    """Sigma' = J Sigma_cam J^T + 0.3 I = (J M)(J M)^T + 0.3 I, Sigma_cam = W Sigma W^T = M M^T,
    J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]].

    points_in_cam (G, 3), factor_in_cam M (G, 3, 3), K (3, 3) -> (G, 3) as (a, b, c) of
    [[a, b], [b, c]]. Working on the factor keeps it elementwise (no batched 3x3 matmuls, which
    are slow on a CPU). x/z and y/z are clamped to the frustum widened by the guard band (the
    reference's 1.3x), measured from the principal point so off-centre cameras work too.
    Worked example: mean (0.4, -0.2, 2), scales (0.1, 0.05, 0.2), 30deg about
    z, f = 1111 -> eigenvalues 1163.4 and 3311.6 px^2.
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    z = points_in_cam[:, 2:3]
    margin_x, margin_y = (GUARD_BAND - 1) * width / (2 * fx), (GUARD_BAND - 1) * height / (2 * fy)
    u = (points_in_cam[:, 0:1] / z).clamp(-cx / fx - margin_x, (width - cx) / fx + margin_x)
    v = (points_in_cam[:, 1:2] / z).clamp(-cy / fy - margin_y, (height - cy) / fy + margin_y)
    M = factor_in_cam
    row0 = (fx / z) * (M[:, 0] - u * M[:, 2])  # first row of J M, (G, 3)
    row1 = (fy / z) * (M[:, 1] - v * M[:, 2])
    return torch.stack(
        [(row0 * row0).sum(-1) + DILATION, (row0 * row1).sum(-1), (row1 * row1).sum(-1) + DILATION],
        -1,
    )


def conic_from_cov2d(cov2d: Tensor) -> tuple[Tensor, Tensor]:
    """Sigma'^-1 = [[c, -b], [-b, a]] / (ac - b^2) for cov2d (..., 3) = (a, b, c).

    Returns conic (..., 3) and a validity mask (...,). The matrix is first divided by its half
    trace, so det and inverse stay in range for determinants from ~1e-30 to ~1e30 in float32
    (no overflow/underflow of ac or b^2); non-positive or non-finite determinants are invalid
    and get a zero conic.
    """
    finite = torch.isfinite(cov2d).all(-1, keepdim=True)
    # Non-finite rows are swapped for I before any arithmetic so no NaN reaches the gradients.
    a, b, c = torch.where(finite, cov2d, cov2d.new_tensor([1.0, 0.0, 1.0])).unbind(-1)
    s = (0.5 * (a + c)).abs().clamp_min(torch.finfo(cov2d.dtype).tiny)
    an, bn, cn = a / s, b / s, c / s
    det_n = an * cn - bn * bn
    valid = (det_n > 0) & torch.isfinite(det_n) & finite[..., 0]
    inv = torch.where(
        valid, 1.0 / (det_n.where(valid, torch.ones_like(det_n)) * s), torch.zeros_like(det_n)
    )
    return torch.stack([cn * inv, -bn * inv, an * inv], -1), valid


def radius_3sigma(cov2d: Tensor) -> Tensor:
    """ceil(3 sqrt(lambda_max)), lambda_max = mid + sqrt(max(0.1, mid^2 - det)), mid = (a+c)/2.

    (..., 3) -> (...,) float pixels (the reference's screen-space extent from the larger
    eigenvalue; 0.1 keeps the square root away from rounding noise on round splats).
    """
    a, b, c = cov2d.detach().unbind(-1)
    # mid^2 - det = ((a - c)/2)^2 + b^2: hypot has no cancellation and no overflow.
    half_gap = torch.hypot(0.5 * (a - c), b).clamp_min(0.1**0.5)
    return torch.ceil(3.0 * torch.sqrt(0.5 * (a + c) + half_gap))


def sh_colors(means: Tensor, sh: Tensor, degree: int, camera_center: Tensor) -> Tensor:
    """c = max(SH_degree(sh, d) + 0.5, 0), d = (mu - o) / |mu - o| (the reference's offset/clamp).

    means (G, 3), sh (G, K, 3), camera_center (3,) -> (G, 3).
    """
    dirs = means - camera_center
    dirs = dirs * torch.rsqrt((dirs * dirs).sum(-1, keepdim=True).clamp_min(1e-20))
    return torch.clamp_min(eval_sh(degree, sh, dirs) + 0.5, 0.0)


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    K: Tensor,
    cam_from_world: Tensor,
    width: int,
    height: int,
    near: float = 0.01,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """EWA projection of G world-space Gaussians into one camera.

    means (G, 3), quats (G, 4), log_scales (G, 3), K (3, 3), cam_from_world (4, 4) ->
    means2d (G, 2), conics (G, 3), depths (G,), radii (G,). A Gaussian is culled (radius 0)
    when its centre is not beyond the near plane, its 2D covariance is degenerate, or its
    3-sigma box misses the image.
    """
    Rw, tw = cam_from_world[:3, :3], cam_from_world[:3, 3]
    p_cam = means @ Rw.T + tw
    depths = p_cam[:, 2]
    in_front = depths > near
    # Culled Gaussians get a harmless depth so no division by ~0 leaks NaN into the gradients.
    p_safe = torch.where(in_front[:, None], p_cam, p_cam.new_tensor([0.0, 0.0, 1.0]))
    factor_cam = (covariance_factor(quats, log_scales).transpose(1, 2) @ Rw.T).transpose(1, 2)
    cov2d = ewa_covariance_2d(p_safe, factor_cam, K, width, height)
    conics, valid = conic_from_cov2d(cov2d)
    uv = p_safe[:, :2] / p_safe[:, 2:3]
    means2d = torch.stack([K[0, 0] * uv[:, 0] + K[0, 2], K[1, 1] * uv[:, 1] + K[1, 2]], -1)
    radii = radius_3sigma(cov2d)
    m = means2d.detach()
    on_image = (
        (m[:, 0] + radii > 0)
        & (m[:, 0] - radii < width)
        & (m[:, 1] + radii > 0)
        & (m[:, 1] - radii < height)
    )
    keep = in_front & valid & on_image & torch.isfinite(radii)
    radii = torch.where(keep, radii, torch.zeros_like(radii))
    return means2d, conics, depths, radii
