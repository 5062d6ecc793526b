"""Learnt per-camera pose corrections: a twist xi_i = (rho_i, phi_i) in se(3) per training
camera (the camera optimisers of nerfstudio and gsplat; Lin et al. 2021, "BARF", Sec. 3),
applied on the camera side, about a pivot on the optical axis:

    cam_from_world_i' = P_i^-1 exp(xi_i) P_i cam_from_world_i,   P_i x = x - d_i e_z,

i.e. the left perturbation D_i = [R, t + d_i (I - R) e_z] with [R, t] = exp(xi_i), in the frame
the image is formed in: rho_i moves the camera along its own axes, phi_i turns it about the
point at depth d_i in front of it, and the camera centre moves by |t + d_i (I - R) e_z|.

Why the camera side: a correction on the world side, cam_from_world exp(xi), would turn the
camera about the world origin, so its meaning would depend on where the origin happens to be.
Why the pivot: turned about its optical centre (d = 0), a camera's image shifts by about f |phi|
as a whole, which a sideways step of d |phi| (d = depth of the scene) nearly reproduces; the loss
then has a long narrow valley along that mix, and Adam, which scales each coordinate on its
own, crawls along it. Turned about a point at the scene's depth, phi leaves the middle of the
image in place and mostly changes parallax while rho shifts the image: nearly separate
coordinates. (Measured on sample_data, frozen scene, one camera off by 1 deg and 2 % of the
scene, Adam at lr 1e-3: 50 steps to 0.22 deg / 0.0033 about the pivot, 150 steps to 0.29 deg /
0.0047 about the optical centre.)

After each step the twists lose their component along 12 modes the photometric loss cannot
hold (`gauge_basis`, `PoseCorrection.remove_gauge`): one rigid motion of the world applied to
every camera (the scene can follow it exactly), and the 6 twists all cameras share in their own
frames (a common step forward trades against the scene's scale, a common pitch about the pivots
of an orbit against squashing the scene in height). Left free, these drift and carry the scene
away from the cameras that are not corrected (held-out views). On sample_data (35 views, one off
by 1 deg, 800 steps) the common rotation of the other cameras was 0.13-0.15 deg with only the
shared twists removed and 0.02-0.03 deg with both; in a variant with neither (lr 1e-3) the other
cameras had drifted 0.29 deg on average by step 500, 0.27 deg of it a common pitch.

What the loss can hold is still noisy: against a scene being fitted, an exact camera's
photometric optimum lies a quarter of a pixel to a pixel from the truth, so exact cameras refined
from the start wander and the scene follows them. Cameras therefore start on probation: for the
first passes their corrections stay at zero (the images are formed at the given poses, so the
scene follows nothing) while `observe` sums each camera's pose gradient at its given pose; then
`release` frees only the cameras the scene disagrees with, those whose mean gradient (its part
the loss can hold, `gauge_basis`) is an outlier among all cameras' (`outlier_ratios`), and holds
the others at their given poses for the rest of the run; the held ones fix the gauge.
C = cameras.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from recon.cameras.cameras import Cameras
from recon.cameras.se3 import se3_adjoint, se3_exp


def pivot_corrections(twists: Tensor, pivots: Tensor) -> Tensor:
    """D = P^-1 exp(xi) P, P = translation by -d e_z, in float64.  (C, 6), (C,) -> (C, 4, 4).
    Zero twists give the identity exactly; d = 0 gives exp(xi)."""
    D = se3_exp(twists.double())
    R = D[:, :3, :3]
    e_z = torch.zeros_like(D[:, :3, 3])
    e_z[:, 2] = 1.0
    offset = pivots.double()[:, None] * (e_z - R[:, :, 2])  # d (I - R) e_z
    return torch.cat([torch.cat([R, (D[:, :3, 3] + offset)[..., None]], -1), D[:, 3:]], -2)


def correct_cam_from_world(cam_from_world: Tensor, twists: Tensor, pivots: Tensor) -> Tensor:
    """P^-1 exp(xi) P cam_from_world, composed in float64.  (C, 4, 4), (C, 6), (C,) ->
    (C, 4, 4) in the dtype of cam_from_world; zero twists return cam_from_world exactly."""
    corrected = pivot_corrections(twists, pivots) @ cam_from_world.double()
    return corrected.to(cam_from_world.dtype)


def correct_cameras(cameras: Cameras, twists: Tensor, pivots: Tensor) -> Cameras:
    """C cameras with `correct_cam_from_world` applied (differentiable in twists (C, 6))."""
    return Cameras(
        cameras.K,
        correct_cam_from_world(cameras.cam_from_world, twists, pivots),
        cameras.width,
        cameras.height,
    )


def pivot_depths(cameras: Cameras, center: Tensor) -> Tensor:
    """Depth of the point `center` (3,) (the scene's centre) in each camera, 0 where it is not
    in front (the pivot is then the optical centre).  -> (C,)."""
    cfw = cameras.cam_from_world.double()
    z = cfw[:, 2, :3] @ center.double().to(cfw.device) + cfw[:, 2, 3]
    return z.clamp_min(0.0)


def gauge_basis(cam_from_world: Tensor, pivots: Tensor) -> Tensor:
    """Orthonormal basis (6C, r), r <= 12, of the corrections the photometric loss cannot hold
    (flattened (C, 6) twists): the 6 twists every camera shares in its own frame, and the 6
    rigid motions M of the world, cam_from_world_i M, i.e. xi_i = Ad(P_i cam_from_world_i) eta
    (`se3_adjoint`). (C, 4, 4), (C,) -> (6C, r) float64; r < 12 where the two overlap (the yaw
    of a ring of cameras about its axis is both)."""
    C = len(cam_from_world)
    P = torch.eye(4, dtype=torch.float64).repeat(C, 1, 1)
    P[:, 2, 3] = -pivots.double().cpu()
    shared = torch.eye(6, dtype=torch.float64).repeat(C, 1)  # (6C, 6)
    world = se3_adjoint(P @ cam_from_world.double().cpu()).reshape(6 * C, 6)
    U, S, _ = torch.linalg.svd(torch.cat([shared, world], 1), full_matrices=False)
    return U[:, S > 1e-9 * S[0]].to(cam_from_world.device)  # an SVD this small: on the CPU


def outlier_ratios(mean_grads: Tensor, gauge: Tensor) -> Tensor:
    """How far each camera's mean pose gradient stands out among the cameras': with g_i its
    part off the gauge modes (`gauge_basis`, which no camera's error shows in), the larger of
    |g_i rho| / median_j |g_j rho| and |g_i phi| / median_j |g_j phi| (translation and
    rotation blocks apart: they have different units). An exact camera's gradient against the
    scene being fitted is its small bias; a camera that is really off pulls consistently and
    stands out. (C, 6) float64, (6C, r) -> (C,) float64.
    Example: block sizes (rho, phi) (1, 1), (1, 1), (1, 2), (8, 1), no gauge -> (1, 1, 2, 8)."""
    g = mean_grads.double().reshape(-1)
    g = (g - gauge.double() @ (gauge.double().T @ g)).reshape(mean_grads.shape)
    size = torch.stack([g[:, :3].norm(dim=-1), g[:, 3:].norm(dim=-1)], -1)  # (C, 2)
    median = size.median(dim=0).values.clamp_min(torch.finfo(torch.float64).tiny)
    return (size / median).max(dim=-1).values


def correction_sizes(twists: Tensor, pivots: Tensor) -> tuple[Tensor, Tensor]:
    """How far each correction moves its camera: rotation angle |phi| in degrees and the
    distance its centre moves, |t of D| (= |o' - o|), in scene units.  -> (C,), (C,)."""
    with torch.no_grad():
        D = pivot_corrections(twists, pivots)
        return torch.rad2deg(twists[:, 3:].double().norm(dim=-1)), D[:, :3, 3].norm(dim=-1)


class PoseCorrection(nn.Module):
    """One zero-initialised twist per training camera, `twists` (C, 6), turning it about a
    pivot at depth `pivots` (C,) (a buffer: saved with the model, never trained), `frozen`
    (C,) cameras held at their given poses (`release`), and the probation's sums of each
    camera's pose gradient `grad_sums` (C, 6) over its `visits` (C,) (`observe`)."""

    def __init__(self, num_cameras: int):
        super().__init__()
        self.twists = nn.Parameter(torch.zeros(num_cameras, 6))
        self.register_buffer("pivots", torch.zeros(num_cameras))
        self.register_buffer("frozen", torch.zeros(num_cameras, dtype=torch.bool))
        self.register_buffer("grad_sums", torch.zeros(num_cameras, 6, dtype=torch.float64))
        self.register_buffer("visits", torch.zeros(num_cameras, dtype=torch.int64))
        self.gauge = None  # (6C, r), set with the cameras (`set_gauge`)

    def reset(self, cameras: Cameras, center: Tensor) -> None:
        """Zero twists for `cameras`, pivots at the depth of `center` (3,) in each."""
        device = self.twists.device
        self.twists = nn.Parameter(torch.zeros(len(cameras), 6, device=device))
        self.pivots = pivot_depths(cameras, center).to(device=device, dtype=self.pivots.dtype)
        self.frozen = torch.zeros(len(cameras), dtype=torch.bool, device=device)
        self.grad_sums = torch.zeros(len(cameras), 6, dtype=torch.float64, device=device)
        self.visits = torch.zeros(len(cameras), dtype=torch.int64, device=device)
        self.set_gauge(cameras)

    def set_gauge(self, cameras: Cameras) -> None:
        """The modes `remove_gauge` projects out, for the training `cameras` (not saved: a
        function of the cameras and the pivots)."""
        self.gauge = gauge_basis(cameras.cam_from_world, self.pivots)

    def resize(self, num_cameras: int) -> None:
        """Empty tensors for `num_cameras` cameras, to load a saved state into."""
        self.twists = nn.Parameter(self.twists.new_empty(num_cameras, 6))
        self.pivots = self.pivots.new_empty(num_cameras)
        self.frozen = self.frozen.new_zeros(num_cameras)
        self.grad_sums = self.grad_sums.new_zeros(num_cameras, 6)
        self.visits = self.visits.new_zeros(num_cameras)

    @torch.no_grad()
    def observe(self, index: int) -> None:
        """Add camera `index`'s pose gradient (the row of `twists.grad`, taken at its given
        pose while on probation) to its sum, and count the visit."""
        if self.twists.grad is not None:
            self.grad_sums[index] += self.twists.grad[index].double()
            self.visits[index] += 1

    @torch.no_grad()
    def release(self, min_ratio: float) -> int:
        """End the probation: free the cameras whose mean pose gradient is more than
        `min_ratio` times the median camera's (`outlier_ratios`), hold the others at their
        given poses from now on; returns how many are free."""
        mean = self.grad_sums / self.visits.clamp_min(1)[:, None]
        ratios = outlier_ratios(mean.cpu(), self.gauge).to(self.frozen.device)
        self.frozen |= ~(ratios > min_ratio)
        self.hold_frozen()
        return int((~self.frozen).sum())

    @torch.no_grad()
    def hold_frozen(self) -> None:
        """Zero the twists of the frozen cameras (after each optimizer step: Adam's momentum
        would move them even without a gradient)."""
        self.twists[self.frozen] = 0.0

    @torch.no_grad()
    def remove_gauge(self) -> None:
        """Project the twists onto the complement of `gauge_basis` (after each optimizer step
        while no camera is frozen: frozen cameras, held at their given poses, fix the gauge)."""
        if bool(self.frozen.any()):
            return
        x = self.twists.detach().double().cpu().reshape(-1)
        x = x - self.gauge @ (self.gauge.T @ x)
        self.twists.copy_(x.reshape(self.twists.shape))

    def forward(self, cameras: Cameras, indices: Tensor | list[int]) -> Cameras:
        """The cameras `indices` of the training set `cameras`, corrected."""
        indices = torch.as_tensor(indices, dtype=torch.long, device=self.twists.device)
        return correct_cameras(cameras[indices], self.twists[indices], self.pivots[indices])

    def stats(self) -> dict[str, float]:
        """Mean and largest correction: rotation in degrees, centre shift in scene units; and
        how many cameras are held at their given poses (`release`)."""
        if len(self.twists) == 0:
            return {}
        degrees, shift = correction_sizes(self.twists, self.pivots)
        return {
            "pose_rot_deg_mean": float(degrees.mean()),
            "pose_rot_deg_max": float(degrees.max()),
            "pose_shift_mean": float(shift.mean()),
            "pose_shift_max": float(shift.max()),
            "pose_frozen": float(self.frozen.sum()),
        }
