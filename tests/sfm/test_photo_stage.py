"""`recon sfm PHOTOS` end to end on the project's own sample scene, through the CLI: every view
registers and the poses match the generator's ground truth (issue: median rotation <= 0.2 deg)."""

import json

import pytest

from tests.conftest import SAMPLE_DATA, recon_cli


@pytest.mark.slow
def test_sample_photos_register_with_accurate_poses(tmp_path):
    ws = tmp_path / "ws"
    report = json.loads(
        recon_cli("sfm", str(SAMPLE_DATA / "images"), "-w", str(ws), "--json").stdout
    )
    assert (
        report["images_given"] == report["images_registered"] == 40 and report["unregistered"] == []
    )
    assert json.loads((ws / "sfm" / "report.json").read_text())["images_registered"] == 40
    out = json.loads(
        recon_cli(
            "eval", "-w", str(ws), "--gt-poses", str(SAMPLE_DATA / "transforms.json"), "--json"
        ).stdout
    )
    pose = out["sfm"]["pose"]
    assert pose["matched"] == 40
    assert pose["median_rotation_error_deg"] <= 0.2
    assert pose["median_center_error_pct"] <= 0.5
    assert json.loads((ws / "sfm" / "pose_accuracy.json").read_text()) == pose
