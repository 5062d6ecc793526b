"""Initial Gaussians from points (SfM or random in the scene box), as the reference: isotropic
scale = sqrt(mean squared distance to the 3 nearest neighbours), identity rotation, a fixed
opacity, and a degree-0 SH colour with SH_0 c + 0.5 = the point colour."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from recon.fields.sh import C0, num_sh_bases
from recon.gaussians.ply import read_splat_ply

MIN_SQ_DIST = 1e-7  # the reference's floor: duplicate points still get a finite log-scale


def knn_scales(points: np.ndarray, k: int = 3) -> np.ndarray:
    """s_i = sqrt(mean_{j in kNN(i)} |p_i - p_j|^2), floored. (N, 3) -> (N,).
    Example: points on a unit-spaced line -> s = sqrt((1 + 1 + 4) / 3) = sqrt(2) inside."""
    if len(points) < 2:
        return np.ones(len(points))
    k = min(k, len(points) - 1)
    dist, _ = cKDTree(points).query(points, k=k + 1)  # the first neighbour is the point itself
    return np.sqrt(np.maximum((dist[:, 1:] ** 2).mean(1), MIN_SQ_DIST))


def gaussians_from_points(
    points: Tensor, colors: Tensor, sh_degree: int, opacity: float
) -> dict[str, Tensor]:
    """points (N, 3), colors (N, 3) in [0, 1] -> means, quats, log_scales, opacity_logits,
    sh_dc (N, 1, 3), sh_rest (N, (degree+1)^2 - 1, 3), all float32 on the points' device."""
    n, device = points.shape[0], points.device
    scales = knn_scales(points.detach().cpu().double().numpy())
    quats = torch.zeros(n, 4, device=device)
    quats[:, 0] = 1.0
    return {
        "means": points.float().clone(),
        "quats": quats,
        "log_scales": torch.log(torch.as_tensor(scales, dtype=torch.float32, device=device))[
            :, None
        ].repeat(1, 3),
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


def uses_random_init(config, scene) -> bool:
    """init = random, or init = sfm without SfM points."""
    if config.init not in ("sfm", "random"):
        raise ValueError(f"init must be 'sfm' or 'random', got {config.init!r}")
    return config.init == "random" or scene.points is None or len(scene.points) == 0


def initial_gaussians(config, scene) -> dict[str, Tensor]:
    """Gaussians for `config` (init, init_points, sh_degree, init_opacity, seed) and a SceneInfo."""
    if not uses_random_init(config, scene):
        points = scene.points.float().cpu()
        colors = (
            scene.point_colors.float().cpu()
            if scene.point_colors is not None
            else torch.full_like(points, 0.5)
        )
    else:
        points, colors = random_points(scene.aabb, config.init_points, config.seed)
    return gaussians_from_points(points, colors, config.sh_degree, config.init_opacity)


def image_colors(points: Tensor, images: Tensor, cameras) -> tuple[Tensor, Tensor]:
    """Median colour of each point over the training views that see it (nearest pixel, no
    occlusion test) and how many views see it. points (N, 3), images (C, H, W, 3) ->
    colours (N, 3), counts (N,)."""
    C, H, W, _ = images.shape
    K, cfw = cameras.K.to(points), cameras.cam_from_world.to(points)
    p_cam = points[None] @ cfw[:, :3, :3].transpose(1, 2) + cfw[:, None, :3, 3]  # (C, N, 3)
    z = p_cam[..., 2]
    zs = z.clamp_min(1e-9)
    u = K[:, None, 0, 0] * p_cam[..., 0] / zs + K[:, None, 0, 2]
    v = K[:, None, 1, 1] * p_cam[..., 1] / zs + K[:, None, 1, 2]
    seen = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    col, row = u.clamp(0, W - 1).long(), v.clamp(0, H - 1).long()
    views = torch.arange(C, device=points.device)[:, None].expand_as(col)
    samples = images.to(points)[views, row, col]  # (C, N, 3)
    samples = torch.where(seen[..., None], samples, torch.full_like(samples, float("nan")))
    return torch.nanmedian(samples, dim=0).values, seen.sum(0)


def sample_in_hull(
    aabb: Tensor,
    n: int,
    images: Tensor,
    cameras,
    background: Tensor,
    seed: int,
    tolerance: float = 0.02,
    rounds: int = 20,
) -> tuple[Tensor, Tensor]:
    """Up to n uniform points of the box whose median colour over the views that see them is
    not the background (a visual hull, for captures composited on a plain background), with
    those colours. Where every view sees the object nothing is rejected, so on real captures
    this is random init with image colours. -> points (M, 3), colours (M, 3), M <= n."""
    gen = torch.Generator().manual_seed(seed)
    lo, hi = aabb[0].float().cpu(), aabb[1].float().cpu()
    kept_p, kept_c, total = [], [], 0
    for _ in range(rounds):
        points = lo + (hi - lo) * torch.rand(n, 3, generator=gen)
        colors, counts = image_colors(points, images.cpu(), cameras.to("cpu"))
        off_bg = (colors - background.float().cpu()).abs().amax(-1) > tolerance
        keep = (counts > 0) & off_bg
        kept_p.append(points[keep])
        kept_c.append(colors[keep])
        total += int(keep.sum())
        if total >= n:
            break
    return torch.cat(kept_p)[:n], torch.cat(kept_c)[:n].clamp(0, 1)


def sample_in_shell(
    center: Tensor,
    centers: Tensor,
    factor: float,
    n: int,
    images: Tensor,
    cameras,
    seed: int,
    rounds: int = 20,
) -> tuple[Tensor, Tensor]:
    """Up to n points uniform in the volume of the shell r0 <= |x - center| <= factor r0 that
    some view sees, with their median image colours; r0 = 1.1 x the largest camera distance
    from `center`. Unbounded captures keep their background out there; a shell beyond every
    camera keeps initial Gaussians from sitting in front of a lens and filling whole images.
    center (3,), centers (C, 3) camera centres -> points (M, 3), colours (M, 3), M <= n."""
    gen = torch.Generator().manual_seed(seed)
    center = center.float().cpu()
    r0 = 1.1 * float((centers.float().cpu() - center).norm(dim=-1).max())
    r1 = factor * r0
    kept_p, kept_c, total = [], [], 0
    for _ in range(rounds):
        d = torch.randn(n, 3, generator=gen)
        d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        u = torch.rand(n, 1, generator=gen)
        r = (r0**3 + u * (r1**3 - r0**3)) ** (1 / 3)  # uniform in the shell's volume
        points = center + r * d
        colors, counts = image_colors(points, images.cpu(), cameras.to("cpu"))
        kept_p.append(points[counts > 0])
        kept_c.append(colors[counts > 0])
        total += int((counts > 0).sum())
        if total >= n:
            break
    return torch.cat(kept_p)[:n], torch.cat(kept_c)[:n].clamp(0, 1)


def sh_degree_in_use(sh: np.ndarray) -> int:
    """Highest degree l with a non-zero coefficient in sh (G, K, 3); 0 if only DC is set."""
    degree = round(float(np.sqrt(sh.shape[1]))) - 1
    while degree > 0 and not np.any(sh[:, degree * degree : (degree + 1) ** 2]):
        degree -= 1
    return degree


def gaussians_from_splat_ply(
    path, scene_from_world, sh_degree: int
) -> tuple[dict[str, Tensor], int]:
    """An INRIA splat PLY in WORLD units (as `recon export` writes it) -> the model's attribute
    tensors in the normalized scene frame x_scene = s R x_world + t, and the SH degree the file
    uses (capped at sh_degree). The inverse of `export.splat.gaussians_to_world`, which it is:
    that function with the inverse similarity (1/s, R^T, -R^T t / s) (means, log-scales - ln(1/s),
    rotations R q, SH rotated per degree). SH above sh_degree are dropped."""
    from recon.gaussians.transform import gaussians_to_world

    g = read_splat_ply(path)
    s, R, t = (
        float(scene_from_world.scale),
        np.asarray(scene_from_world.R, float),
        np.asarray(scene_from_world.t, float),
    )
    g = {k: v.astype(np.float64) for k, v in g.items()}
    scene = gaussians_to_world(g, 1.0 / s, R.T, -(R.T @ t) / s)
    K = num_sh_bases(sh_degree)
    sh = torch.from_numpy(scene["sh"][:, :K]).float()
    out = {
        name: torch.from_numpy(np.ascontiguousarray(scene[name])).float()
        for name in ("means", "quats", "log_scales", "opacity_logits")
    }
    out["sh_dc"], out["sh_rest"] = sh[:, :1].contiguous(), sh[:, 1:].contiguous()
    return out, min(sh_degree_in_use(g["sh"]), sh_degree)
