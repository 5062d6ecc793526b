"""Initial Gaussians from points (SfM or random in the scene box), as the reference: isotropic
scale = sqrt(mean squared distance to the 3 nearest neighbours), identity rotation, a fixed
opacity, and a degree-0 SH colour with SH_0 c + 0.5 = the point colour."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from recon.fields.sh import C0, num_sh_bases

MIN_SQ_DIST = 1e-7  # the reference's floor: duplicate points still get a finite log-scale


def knn_scales(points: np.ndarray, k: int = 3) -> np.ndarray:
    """s_i = sqrt(mean_{j in kNN(i)} |p_i - p_j|^2), floored. (N, 3) -> (N,).
    Example: points on a unit-spaced line -> s = sqrt((1 + 1 + 4) / 3) = sqrt(2) inside."""
    if len(points) < 2:
        return np.ones(len(points))
    k = min(k, len(points) - 1)
    dist, _ = cKDTree(points).query(points, k=k + 1)  # the first neighbour is the point itself
    return np.sqrt(np.maximum((dist[:, 1:] ** 2).mean(1), MIN_SQ_DIST))


def gaussians_from_points(points: Tensor, colors: Tensor, sh_degree: int,
                          opacity: float) -> dict[str, Tensor]:
    """points (N, 3), colors (N, 3) in [0, 1] -> means, quats, log_scales, opacity_logits,
    sh_dc (N, 1, 3), sh_rest (N, (degree+1)^2 - 1, 3), all float32 on the points' device."""
    n, device = points.shape[0], points.device
    scales = knn_scales(points.detach().cpu().double().numpy())
    quats = torch.zeros(n, 4, device=device)
    quats[:, 0] = 1.0
    return {
        "means": points.float().clone(),
        "quats": quats,
        "log_scales": torch.log(torch.as_tensor(scales, dtype=torch.float32, device=device))[:, None]
        .repeat(1, 3),
        "opacity_logits": torch.full((n,), float(np.log(opacity / (1 - opacity))), device=device),
        "sh_dc": ((colors.float() - 0.5) / C0)[:, None, :].clone(),
        "sh_rest": torch.zeros(n, num_sh_bases(sh_degree) - 1, 3, device=device),
    }


def random_points(aabb: Tensor, n: int, seed: int) -> tuple[Tensor, Tensor]:
    """n uniform points in the box aabb (2, 3) and uniform random colours."""
    gen = torch.Generator().manual_seed(seed)
    lo, hi = aabb[0].float().cpu(), aabb[1].float().cpu()
    points = lo + (hi - lo) * torch.rand(n, 3, generator=gen)
    return points, torch.rand(n, 3, generator=gen)


def initial_gaussians(config, scene) -> dict[str, Tensor]:
    """Gaussians for `config` (init, init_points, sh_degree, init_opacity, seed) and a SceneInfo."""
    use_sfm = config.init == "sfm" and scene.points is not None and len(scene.points) > 0
    if config.init not in ("sfm", "random"):
        raise ValueError(f"init must be 'sfm' or 'random', got {config.init!r}")
    if use_sfm:
        points = scene.points.float().cpu()
        colors = (scene.point_colors.float().cpu() if scene.point_colors is not None
                  else torch.full_like(points, 0.5))
    else:
        points, colors = random_points(scene.aabb, config.init_points, config.seed)
    return gaussians_from_points(points, colors, config.sh_degree, config.init_opacity)
