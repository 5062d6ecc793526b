"""Helpers shared by the volume models (nerf, ngp): ray batches, image rendering in chunks,
small MLPs, the truncated exponential and scene bounds. No rendering maths lives here (that is
`recon.volrend`)."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

from recon.cameras import Cameras, camera_rays
from recon.models.base import SceneInfo, TrainData
from recon.volrend import normalize_to_box, ray_aabb_intersect, surface_depth

# render_rays(origins (R, 3), directions (R, 3)) -> (rgb (R, 3), expected t (R,), acc (R,))
RenderRaysFn = Callable[[Tensor, Tensor], tuple[Tensor, Tensor, Tensor]]


def sample_rays(data: TrainData, n: int, generator: torch.Generator) -> dict[str, Tensor]:
    """n training rays drawn uniformly with replacement from all pixels (`TrainData.rays_at`),
    on the generator's device (the model's: no host copy)."""
    pixels = torch.randint(0, data.num_pixels, (n,), generator=generator, device=generator.device)
    return data.rays_at(pixels)


@torch.no_grad()
def render_image(render_rays: RenderRaysFn, camera: Cameras, chunk: int) -> dict[str, Tensor]:
    """Render camera 0 of `camera` ray chunk by ray chunk.

    Returns rgb (H, W, 3), depth (H, W) = z-depth along the optical axis of the expected hit,
    (sum_i w_i t_i / acc) * z_per_t where acc > 0 (0 elsewhere), and acc (H, W).
    """
    origins, directions, z_per_t = camera_rays(camera, 0)
    H, W = z_per_t.shape
    o, d = origins.reshape(-1, 3).float(), directions.reshape(-1, 3).float()
    parts = [render_rays(o[i : i + chunk], d[i : i + chunk]) for i in range(0, o.shape[0], chunk)]
    rgb, t, acc = (torch.cat(p) for p in zip(*parts))
    depth = surface_depth(t, acc) * z_per_t.reshape(-1).to(t)
    return {"rgb": rgb.reshape(H, W, 3), "depth": depth.reshape(H, W), "acc": acc.reshape(H, W)}


def scatter_rays(values: Tensor, index: Tensor, n: int, fill: Tensor | None) -> Tensor:
    """Per-ray values (K, ...) of the rays `index` (K,) placed into (n, ...) rows, the other rows
    set to `fill` (broadcast to one row; None: 0). Differentiable in `values`."""
    if index.numel() == n:
        return values
    out = torch.zeros((n, *values.shape[1:]), dtype=values.dtype, device=values.device)
    if fill is not None:
        out = out + fill.to(values)
    return out.index_copy(0, index, values)


def ray_bounds(
    scene: SceneInfo, origins: Tensor, directions: Tensor, aabb: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """(t_min, t_max) per ray: the scene box clipped to [near, far] for a bounded scene (rays
    that miss get t_min = t_max, i.e. no samples), [near, far] for an unbounded one. aabb: the
    box (2, 3) on the rays' device, a model's buffer (`scene.aabb` lives on the host: a copy a
    call); None: scene.aabb."""
    R = origins.shape[0]
    near = torch.full((R,), scene.near, device=origins.device, dtype=origins.dtype)
    far = torch.full((R,), scene.far, device=origins.device, dtype=origins.dtype)
    if scene.unbounded:
        return near, far
    box = scene.aabb if aabb is None else aabb
    t0, t1, hit = ray_aabb_intersect(origins, directions, box.to(origins))
    t0, t1 = torch.maximum(t0, near), torch.minimum(t1, far)
    t1 = torch.where(hit & (t1 > t0), t1, t0)
    return t0, t1


def points_in_box(scene: SceneInfo) -> Tensor | None:
    """The scene's SfM points (P, 3) that lie in its box, or None when it has none. The box is
    fitted to the robust bulk of the points; those outside it are the sparse, noisy tail and
    the far field, where one contracted occupancy cell spans a vast region: marking them would
    make whole shells of the far field occupied."""
    if scene.points is None or not len(scene.points):
        return None
    inside = (normalize_to_box(scene.points, scene.aabb.to(scene.points)).abs() <= 1.0).all(-1)
    return scene.points[inside] if inside.any() else None


def mlp_dtype(device: torch.device, precision: str) -> torch.dtype:
    """The dtype MLP matmuls run in under autocast: fp32, or bf16 where the hardware multiplies
    bf16 natively (a CUDA GPU with bf16, a CPU with AVX512-BF16 or AMX: 3x the fp32 matmul rate
    measured on this project's 2-core VM). precision: "fp32" | "bf16" | "auto" (bf16 when native).
    Weights, optimizer state and the volume rendering stay fp32 either way."""
    if precision not in ("auto", "fp32", "bf16"):
        raise ValueError(f"precision must be auto, fp32 or bf16, got {precision!r}")
    if precision == "fp32":
        return torch.float32
    if precision == "bf16":
        return torch.bfloat16
    if device.type == "cuda":
        native = torch.cuda.is_bf16_supported()
    else:
        probes = (
            "_is_avx512_bf16_supported",
            "_is_amx_tile_supported",
        )  # private torch API: absent = no
        native = any(getattr(torch.cpu, name, lambda: False)() for name in probes)
    return torch.bfloat16 if native else torch.float32


def mlp(in_dim: int, width: int, n_hidden: int, out_dim: int) -> nn.Sequential:
    """in -> [Linear(width) -> ReLU] x n_hidden -> Linear(out)."""
    layers: list[nn.Module] = []
    d = in_dim
    for _ in range(n_hidden):
        layers += [nn.Linear(d, width), nn.ReLU()]
        d = width
    layers.append(nn.Linear(d, out_dim))
    return nn.Sequential(*layers)


class _TruncExp(torch.autograd.Function):
    """exp(x) forward; backward uses exp(min(x, 15)) so one huge activation cannot explode the
    step (the Instant-NGP / torch-ngp density activation)."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, g: Tensor) -> Tensor:
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(max=15.0))


def trunc_exp(x: Tensor) -> Tensor:
    """sigma = exp(x) with the gradient clamped at x = 15 (see `_TruncExp`)."""
    return _TruncExp.apply(x)


def batch_pixels(
    samples_per_batch: int, default_samples: int, default_rays: int, n_rays: int
) -> int:
    """The rays a training step of a sample-targeted batch fits (`Model.step_pixels`): with a
    sample target, `default_rays` (what the default target `default_samples` fits) scaled by
    the target, whatever the scene's samples a ray; without one, the fixed batch `n_rays`.
    Example: a target 4x the default's that fits 2,500 rays -> 10,000."""
    if samples_per_batch > 0:
        return round(default_rays * samples_per_batch / default_samples)
    return n_rays
