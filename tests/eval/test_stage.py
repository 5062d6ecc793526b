"""`recon eval` (recon.eval.stage): the scores at the training size and at the photos' size."""

import json

from tests.conftest import recon_cli, sphere_workspace


def test_eval_scores_a_coarser_trained_run_at_the_photos_size_too(tmp_path):
    ws = sphere_workspace(tmp_path, n_train=6, n_test=2, size=32)
    recon_cli("train", "-w", str(ws), "-m", "3dgs", "--steps", "20", "--downscale", "2")
    recon_cli("eval", "-w", str(ws), "--run", "3dgs", "--no-lpips", "--no-pictures")
    m = json.loads((ws / "runs" / "3dgs" / "eval" / "metrics.json").read_text())
    assert m["resolution"] == [16, 16]  # the training size, as before
    at = m["photo_size"]
    assert at["resolution"] == [32, 32] and at["downscale"] == 1
    for scores in (at["mean"], at["upsampled"]):
        assert 5 < scores["psnr"] < 60 and 0 < scores["ssim"] <= 1
    assert at["mean"]["psnr"] != at["upsampled"]["psnr"]  # two different images were scored
    report = (ws / "report.md").read_text()
    assert "photos' size" in report and "| 32×32 |" in report
    assert "At the photos' own size, 32×32" in (ws / "report.html").read_text()
    # scored at the photos' size, or with --no-photo-size, there is one size alone
    recon_cli(
        "eval", "-w", str(ws), "--run", "3dgs", "--no-lpips", "--no-pictures", "--downscale", "1"
    )
    m = json.loads((ws / "runs" / "3dgs" / "eval" / "metrics.json").read_text())
    assert m["resolution"] == [32, 32] and "photo_size" not in m
    recon_cli(
        "eval", "-w", str(ws), "--run", "3dgs", "--no-lpips", "--no-pictures", "--no-photo-size"
    )
    assert "photo_size" not in json.loads(
        (ws / "runs" / "3dgs" / "eval" / "metrics.json").read_text()
    )
