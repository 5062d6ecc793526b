"""A picture of the sfm stage: every camera as a frustum (training views blue, held-out orange)
over the sparse points, in the scene frame, for report.html."""

from __future__ import annotations

import numpy as np

from recon.workspace import Workspace, atomic_path

MAX_POINTS = 20_000


def frustum_lines(K: np.ndarray, world_from_cam: np.ndarray, w: int, h: int, depth: float):
    """The 8 segments (8, 2, 3) of a camera's viewing pyramid cut at `depth`: centre to the four
    image corners, and the corners' rectangle."""
    corners_px = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)
    rays = np.c_[(corners_px - K[:2, 2]) / np.diag(K)[:2], np.ones(4)] * depth
    corners = rays @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
    centre = world_from_cam[:3, 3]
    return np.array(
        [[centre, c] for c in corners] + [[corners[i], corners[(i + 1) % 4]] for i in range(4)]
    )


def plot_sfm(ws: Workspace, scene) -> None:
    """scene (`load_scene` with its points) -> ws.sfm_plot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    cams = scene.cameras(list(range(len(scene.frames))), "cpu")
    world_from_cam = np.linalg.inv(cams.cam_from_world.numpy())
    centres = world_from_cam[:, :3, 3]
    spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).max()) or 1.0
    test = set(scene.split("test"))
    fig = plt.figure(figsize=(7, 6), dpi=110)
    ax = fig.add_subplot(projection="3d")
    points = scene.info.points
    if points is not None and len(points):
        p = points.numpy()
        pick = np.random.default_rng(0).permutation(len(p))[:MAX_POINTS]
        colours = scene.info.point_colors
        c = colours.numpy()[pick] if colours is not None else "0.4"
        ax.scatter(*p[pick].T, s=0.5, c=c, depthshade=False)
    for split, colour in (("train", "tab:blue"), ("test", "tab:orange")):
        idx = [i for i in range(len(scene.frames)) if (i in test) == (split == "test")]
        segments = [
            seg
            for i in idx
            for seg in frustum_lines(
                cams.K[i].numpy(),
                world_from_cam[i],
                int(cams.width[i]),
                int(cams.height[i]),
                0.08 * spread,
            )
        ]
        if segments:
            ax.add_collection3d(
                Line3DCollection(
                    segments, colors=colour, linewidths=0.7, label=f"{split} ({len(idx)})"
                )
            )
    lo, hi = centres.min(0) - 0.1 * spread, centres.max(0) + 0.1 * spread
    middle, half = (lo + hi) / 2, (hi - lo).max() / 2
    for axis, m in zip("xyz", middle):
        getattr(ax, f"set_{axis}lim")(m - half, m + half)
    ax.set_title(
        f"{len(scene.frames)} cameras, {0 if points is None else len(points)} sparse points"
    )
    ax.legend(loc="upper right")
    fig.tight_layout()
    with atomic_path(ws.sfm_plot) as tmp:
        fig.savefig(tmp)
    plt.close(fig)
