"""The `sfm` stage: validate the input, build the scene in temporary folders, swap it into the
workspace, and record the stage (config, input hashes, versions, timing)."""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict
from pathlib import Path

from recon.sfm.scene_writer import SceneConfig, write_scene
from recon.sfm.sources import PosedImages
from recon.workspace import Workspace, atomic_dir


def write_sfm_stage(
    ws: Workspace,
    posed: PosedImages,
    cfg: SceneConfig,
    inputs: dict[str, Path],
    config_record: dict,
    report: dict | None = None,
    progress=None,
    copy_into_sfm: dict[str, Path] | None = None,
) -> dict:
    """Write images/ and sfm/ atomically from posed images and record the `sfm` stage.
    `copy_into_sfm` maps names under sfm/ to files or folders to keep there (COLMAP's database)."""
    started = time.time()
    with ws.writer_lock("sfm"):
        with atomic_dir(ws.images_dir) as images_tmp, atomic_dir(ws.sfm_dir) as sfm_tmp:
            summary = write_scene(posed, cfg, images_tmp, sfm_tmp, ws.rel(ws.images_dir), progress)
            full_report = {**(report or {}), **summary}
            (sfm_tmp / Workspace.SFM_REPORT).write_text(json.dumps(full_report, indent=2) + "\n")
            for name, src in (copy_into_sfm or {}).items():
                dst = sfm_tmp / name
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copytree(src, dst) if Path(src).is_dir() else shutil.copy2(src, dst)
        ended = time.time()
        ws.record_stage(
            "sfm",
            config={**config_record, **asdict(cfg)},
            inputs=inputs,
            outputs={"cameras": ws.cameras_json, "images": ws.images_dir},
            upstream=[],
            started=started,
            ended=ended,
            extra={"summary": summary},
        )
    return full_report
