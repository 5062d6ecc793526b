"""Pose accuracy of the `sfm` stage against reference poses (Sim3-aligned: Umeyama 1991)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon.metrics.pose import pose_errors
from recon.sfm.sources import read_colmap, read_transforms
from recon.workspace import Workspace, WorkspaceError


def sfm_pose_accuracy(ws: Workspace, reference: Path) -> dict:
    """Match our registered images to the reference by file stem; errors after Sim3 alignment
    with one common camera-frame rotation removed (references solved with other intrinsics)."""
    ref = (
        read_transforms(reference)
        if reference.suffix == ".json" or (reference / "transforms.json").exists()
        else read_colmap(reference)
    )
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
    }
