"""`recon sfm PHOTOS`: run the pycolmap engine in a scratch folder inside the workspace, then
write its undistorted model as the workspace scene (same outputs as the pose import)."""

from __future__ import annotations

import dataclasses
import shutil
import tempfile
from pathlib import Path

from recon.sfm.colmap_sfm import SfmConfig, run_sfm
from recon.sfm.scene_writer import SceneConfig
from recon.sfm.sources import read_colmap
from recon.sfm.stage import write_sfm_stage
from recon.workspace import Workspace


def photos_to_workspace(images: Path, ws: Workspace, cfg: SceneConfig, options: dict, progress) -> dict:
    fields = {f.name for f in dataclasses.fields(SfmConfig)}
    config = SfmConfig(**{k: v for k, v in options.items() if k in fields and v is not None})
    work = Path(tempfile.mkdtemp(prefix=".sfm-work-", dir=ws.root))
    try:
        with ws.writer_lock("sfm-engine"):
            result = run_sfm(Path(images), work, config, progress)
        posed = read_colmap(result.images_dir.parent / "sparse", result.images_dir, cfg.holdout_every)
        posed.source = str(images)
        keep = {"colmap/database.db": Path(result.report["paths"]["database"]),
                "colmap/sparse": Path(result.report["paths"]["sparse_distorted"])}
        report = {k: v for k, v in result.report.items() if k != "paths"}
        return write_sfm_stage(ws, posed, cfg, {"photos": Path(images)},
                               {"source": "photos", **dataclasses.asdict(config)}, report, progress,
                               copy_into_sfm={k: v for k, v in keep.items() if v.exists()})
    finally:
        shutil.rmtree(work, ignore_errors=True)
