"""Pose accuracy of the `sfm` stage against reference poses (Sim3-aligned: Umeyama 1991)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon.metrics.pose import pose_errors
from recon.sfm.sources import read_colmap, read_transforms
from recon.workspace import Workspace, WorkspaceError


def read_reference(reference: Path):
    """The reference poses: a transforms.json (or a folder with one) or a COLMAP model."""
    if reference.suffix == ".json" or (reference / "transforms.json").exists():
        return read_transforms(reference)
    return read_colmap(reference)


def reference_observed_fn(reference: Path, tol: float):
    """GT points (reference frame) -> seen by some reference view, from the reference's own
    depth maps (None when it has none): the completeness of a mesh made from SfM poses is then
    measured on the surface the photos show, as for a pose import."""
    from recon.io.exr import read_depth_exr
    from recon.metrics.geometry import observed_by_depth

    frames = read_reference(reference).frames
    if not frames or not all(f.depth_path is not None for f in frames):
        return None
    mats = np.stack([np.linalg.inv(f.world_from_cam) for f in frames])
    Ks = np.stack([f.K for f in frames])
    depths = [read_depth_exr(f.depth_path) for f in frames]
    return lambda points: observed_by_depth(points, mats, Ks, depths, tol)


def sfm_pose_accuracy(ws: Workspace, reference: Path) -> dict:
    """Match our registered images to the reference by file stem; errors after Sim3 alignment
    with one common camera-frame rotation removed (references solved with other intrinsics)."""
    ref = read_reference(reference)
    ours = read_colmap(ws.sparse_dir, ws.images_dir)
    ref_by_name = {f.path.stem: f.world_from_cam for f in ref.frames}
    pairs = [
        (f.world_from_cam, ref_by_name[f.path.stem])
        for f in ours.frames
        if f.path.stem in ref_by_name
    ]
    if len(pairs) < 3:
        raise WorkspaceError(f"only {len(pairs)} images match the reference poses by name (need 3)")
    est, gt = np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])
    e = pose_errors(est, gt, remove_common_rotation=True)
    keep = (
        "median_rotation_error_deg",
        "mean_rotation_error_deg",
        "median_center_error",
        "median_center_error_pct",
        "mean_center_error_pct",
        "common_rotation_deg",
        "reference_diagonal",
    )
    return {
        "status": "ok",
        "reference": str(reference),
        "matched": len(pairs),
        "reference_images": len(ref.frames),
        **{k: float(v) for k, v in e.items() if k in keep and np.isscalar(v)},
        # x_reference = scale rotation x_ours + translation: maps our meshes onto the reference's
        "sim3": {
            "scale": float(e["sim3_scale"]),
            "rotation": np.asarray(e["sim3_rotation"]).tolist(),
            "translation": np.asarray(e["sim3_translation"]).tolist(),
        },
    }
