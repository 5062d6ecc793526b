"""A signed distance field: a multiresolution hash grid (Müller et al. 2022) concatenated with
the position, then a small MLP with Softplus activations whose first output is the signed
distance and the rest a geometry feature (as NeuS2, Wang et al. 2023, Sec. 3).

Initialisation to a sphere: the field is f(x) = (|x| - radius) + g(x), the exact distance to a
sphere about the box centre plus a learnt residual g whose SDF output row starts at zero, so at
step 0 every ray sees a surface to refine and the eikonal term is already zero. (The geometric
initialisation of Atzmon & Lipman 2020, "SAL", Sec. 4, which IDR and NeuS use, gives |x| - radius
only in expectation over the random weights: one draw of a 64-wide network put the zero level
set anywhere between radius 0.27 and beyond 0.8 depending on the direction.) The hidden layers
start N(0, sqrt(2 / width)) with zero bias, and the weights reading the hash features at zero.

The gradient of the SDF (the surface normal, and the eikonal term
E (||grad f|| - 1)^2 of Gropp et al. 2020, "IGR", eq. 2) is exact, by the chain rule:

    grad f = x / |x| + d(MLP)/dx + d(MLP)/d(enc) J,   J = d(enc)/dx (the hash grid's, analytic)

with d(MLP)/d(x, enc) by autograd through the small MLP (create_graph while training, so the
eikonal loss has gradients: a double backward through the MLP only) and J from
`hash_encode_and_jacobian` (the encoding and J in one pass over the corners), linear in the
grid's table and differentiable in it.
"""

from __future__ import annotations

import itertools
import math

import torch
from torch import Tensor, nn

from recon.fields.hashgrid import HashGrid
from recon.fields.hashgrid_jacobian import hash_encode_and_jacobian

SOFTPLUS_BETA = 100.0  # Softplus(100 x) / 100: ReLU-like with a smooth, non-zero second derivative


class SDFField(nn.Module):
    """(points in [-1, 1]^3, the scene box mapped to it) -> signed distance (N,) in those units
    and a geometry feature (N, geo_features)."""

    def __init__(
        self,
        n_levels: int = 16,
        n_features: int = 2,
        log2_table_size: int = 17,
        n_min: int = 16,
        n_max: int = 1024,
        width: int = 64,
        n_hidden: int = 2,
        geo_features: int = 15,
        radius: float = 0.5,
    ):
        super().__init__()
        self.grid = HashGrid(n_levels, n_features, log2_table_size, n_min, n_max)
        dims = [3 + self.grid.out_dim] + [width] * n_hidden + [1 + geo_features]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in itertools.pairwise(dims))
        self.activation = nn.Softplus(beta=SOFTPLUS_BETA)
        self.active_levels = n_levels  # coarse-to-fine: the finer levels read as zero
        self.geometric_init(radius)

    @torch.no_grad()
    def geometric_init(self, radius: float) -> None:
        self.radius = radius
        for i, layer in enumerate(self.layers):
            out_dim = layer.weight.shape[0]
            if i == len(self.layers) - 1:
                layer.weight.normal_(0.0, 1e-4)
                layer.weight[0].zero_()  # the residual starts at zero: f is the sphere
                layer.bias.zero_()
            else:
                layer.weight.normal_(0.0, math.sqrt(2.0) / math.sqrt(out_dim))
                layer.bias.zero_()
                if i == 0:
                    layer.weight[:, 3:].zero_()  # the hash features start switched off

    def level_mask(self, like: Tensor) -> Tensor | None:
        """(L F,) 1 for the features of the active levels, 0 beyond (None: all active)."""
        n_features = self.grid.table.shape[1]
        n_levels = self.grid.out_dim // n_features
        if self.active_levels >= n_levels:
            return None
        mask = torch.zeros(n_levels, n_features, dtype=like.dtype, device=like.device)
        mask[: self.active_levels] = 1.0
        return mask.flatten()

    def _encode(self, u: Tensor) -> Tensor:
        enc = self.grid(u)
        mask = self.level_mask(enc)
        return enc if mask is None else enc * mask

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """x (N, 3) in [-1, 1]^3 -> (sdf (N,), geometry feature (N, geo_features))."""
        h = torch.cat([x, self._encode((x + 1.0) / 2.0)], dim=-1)
        for layer in self.layers[:-1]:
            h = self.activation(layer(h))
        out = self.layers[-1](h)
        return x.norm(dim=-1) - self.radius + out[:, 0], out[:, 1:]

    def sdf(self, x: Tensor) -> Tensor:
        return self(x)[0]

    def with_gradient(self, x: Tensor, create_graph: bool) -> tuple[Tensor, Tensor, Tensor]:
        """(sdf (N,), grad_x sdf (N, 3), geometry feature) at x (N, 3) in [-1, 1]^3, the
        gradient by the chain rule of the module docstring. create_graph: the gradient stays
        differentiable in the parameters (training); x itself is data (no gradient)."""
        x = x.detach()
        u = (x + 1.0) / 2.0  # du/dx = 1/2
        with torch.enable_grad():
            enc, jac = hash_encode_and_jacobian(u, self.grid.table, self.grid.layout)
            mask = self.level_mask(enc)  # (L F,): the masked levels' encoding and Jacobian are 0
            if mask is not None:
                enc, jac = enc * mask, jac * mask[:, None]
            h = torch.cat([x, enc], dim=-1)
            if not h.requires_grad:
                h.requires_grad_(True)
            z = h
            for layer in self.layers[:-1]:
                z = self.activation(layer(z))
            out = self.layers[-1](z)
            (g_h,) = torch.autograd.grad(out[:, 0].sum(), h, create_graph=create_graph)
            radial = x / x.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            grad = radial + g_h[:, :3] + 0.5 * torch.einsum("nj,nja->na", g_h[:, 3:], jac)
        sdf = x.norm(dim=-1) - self.radius + out[:, 0]
        if not create_graph:
            return sdf.detach(), grad.detach(), out[:, 1:].detach()
        return sdf, grad, out[:, 1:]


def sdf_and_gradient(
    field: SDFField, x: Tensor, create_graph: bool
) -> tuple[Tensor, Tensor, Tensor]:
    """(sdf (N,), grad_x sdf (N, 3), geometry feature) at x (N, 3). create_graph: keep the
    gradient differentiable (training, for the eikonal loss and normal-conditioned colour)."""
    return field.with_gradient(x, create_graph)


def eikonal_loss(grad: Tensor) -> Tensor:
    """E (||grad f|| - 1)^2 over the points (IGR, Gropp et al. 2020, eq. 2). grad (N, 3)."""
    return (grad.norm(dim=-1) - 1.0).square().mean()


def sphere_sdf(x: Tensor, radius: float) -> Tensor:
    """|x| - radius: the exact signed distance to a sphere about the origin."""
    return x.norm(dim=-1) - radius


def box_sdf(x: Tensor, half_size: Tensor) -> Tensor:
    """The exact signed distance to an axis-aligned box about the origin (Quilez's form):
    |max(q, 0)| + min(max_k q_k, 0) with q = |x| - half_size."""
    q = x.abs() - half_size
    return q.clamp_min(0.0).norm(dim=-1) + q.max(dim=-1).values.clamp_max(0.0)
