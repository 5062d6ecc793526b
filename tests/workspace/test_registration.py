"""SfM that only half worked: the registration summary (worked example), and through the CLI a
folder of 10 fox photos and 5 noise images: `recon sfm` warns on the terminal with the count and
the commonest reason, records it, writes the model and exits 3 unless --allow-partial; `recon
train` on that workspace says how many images it trains on and repeats the warning."""

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from recon.workspace.registration import partial_warning, reason_kind, registration_summary
from tests.conftest import recon_cli

FOX = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "fox"


def report(usable, registered, reasons):
    return {
        "images_usable": usable,
        "images_registered": registered,
        "unregistered": [{"name": f"{i}.png", "reason": r} for i, r in enumerate(reasons)],
    }


def test_registration_summary_worked_example():
    reasons = [
        "too few matches: best partner image has 3 descriptor matches (40 keypoints); ...",
        "no features: 12 SIFT keypoints (blank, blurred or too dark?)",
        "too few matches: best partner image has 7 descriptor matches (90 keypoints); ...",
    ]
    summary = registration_summary(report(16, 13, reasons), 0.8)
    assert summary["fraction"] == 0.8125 and not summary["partial"]
    summary = registration_summary(report(16, 3, reasons), 0.8)
    assert summary["partial"] and summary["fraction"] == 0.1875
    assert (summary["commonest_reason"], summary["commonest_reason_count"]) == (
        "too few matches",
        2,
    )
    assert partial_warning(summary).startswith(
        "only 3 of 16 usable photos registered (19 %, below --min-registered 0.8); "
        "commonest reason, 2 photos: too few matches: best partner image has 3"
    )
    assert registration_summary(report(4, 4, []), 0.8)["commonest_reason_count"] == 0
    assert registration_summary(report(0, 0, []), 0.8)["partial"]  # nothing usable
    assert reason_kind("registered only in a separate, smaller model (#2): ...") == (
        "registered only in a separate, smaller model"
    )


@pytest.mark.slow
@pytest.mark.skipif(not FOX.exists(), reason="fox data not found beside the repo")
def test_half_registered_capture_warns_and_exits_3(tmp_path):
    src = tmp_path / "photos"
    src.mkdir()
    for path in sorted((FOX / "images").glob("*.jpg"))[:10]:
        Image.open(path).resize((270, 480), Image.LANCZOS).save(src / path.name, quality=95)
    rng = np.random.default_rng(0)
    for k in range(5):
        noise = rng.integers(0, 256, size=(480, 270, 3), dtype=np.uint8)
        Image.fromarray(noise).save(src / f"zz_noise{k}.png")
    ws = tmp_path / "ws"
    args = ("sfm", str(src), "-w", str(ws), "--no-try-harder", "--num-threads", "1")
    proc = recon_cli(*args, check=False)
    assert proc.returncode == 3, proc.stderr
    warning = [line for line in proc.stderr.splitlines() if line.startswith("warning:")]
    assert len(warning) == 1 and "only 10 of 15 usable photos registered (67 %" in warning[0]
    assert "commonest reason, 5 photos:" in warning[0]
    registration = json.loads((ws / "sfm" / "report.json").read_text())["registration"]
    assert registration["partial"] and registration["registered"] == 10
    assert (ws / "sfm" / "cameras.json").exists()  # the model is written all the same

    quiet = recon_cli(*args, "--min-registered", "0.5")
    assert "warning" not in quiet.stderr
    allowed = recon_cli(*args, "--allow-partial")  # exit 0, the warning still printed
    assert "warning: only 10 of 15" in allowed.stderr

    train = recon_cli("train", "-w", str(ws), "--method", "3dgs", "--steps", "2")
    said = train.stdout + train.stderr
    assert "training on 8 images (2 held out); warning: sfm only 10 of 15" in said
