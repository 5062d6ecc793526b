"""The 3D view of report.html and `recon view`, end to end through the CLI on the analytic
sphere: the viewer at a held-out camera draws what `recon render` wrote for it."""

import base64
import io
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest
from PIL import Image

from recon.metrics.image import psnr
from tests.browser import chromium_driver, console_errors
from tests.conftest import recon_cli, write_sphere_dataset

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    """A 3dgs run and a plenoxel run (with its mesh) on the 64 px sphere, evaluated."""
    root = tmp_path_factory.mktemp("viewer")
    data = write_sphere_dataset(root / "sphere", n_train=12, n_test=2, size=64)
    ws = root / "ws"
    recon_cli("sfm", "--from-transforms", str(data), "-w", str(ws))
    recon_cli(
        "train", "-w", str(ws), "--method", "3dgs", "--steps", "300", "--eval-views", "1",
        "--set", "init_points=2000",
    )  # fmt: skip
    recon_cli(
        "train", "-w", str(ws), "--method", "plenoxel", "--steps", "100", "--eval-views", "1",
        "--set", "resolutions=24,48", "--set", "upsample_steps=50",
    )  # fmt: skip
    recon_cli("mesh", "-w", str(ws), "--run", "plenoxel", "--resolution", "64")
    recon_cli("render", "-w", str(ws), "--run", "3dgs")
    recon_cli("eval", "-w", str(ws), "--no-lpips")
    return ws


def snapshot(driver, view: str, camera: int) -> np.ndarray:
    url = driver.execute_script(
        f"const v = window.reconViewers[{view!r}]; v.showCameras = false; v.showPoints = false;"
        f"v.setCamera({camera}, true); return v.snapshot();"
    )
    png = base64.b64decode(url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), np.float32) / 255


def wait_ready(driver, seconds: float = 20) -> None:
    deadline = time.time() + seconds
    while not driver.execute_script("return window.reconViewersReady === true"):
        assert time.time() < deadline, "the viewers never started"
        time.sleep(0.05)


def test_report_viewer_matches_recon_render_at_a_held_out_camera(evaluated):
    ws = evaluated
    page = ws / "report.html"
    text = page.read_text()
    assert 'data-view="3dgs"' in text and 'data-view="plenoxel"' in text
    assert (ws / "viewer" / "viewer.js").exists() and (ws / "viewer" / "3dgs.js").exists()
    with chromium_driver(webgl=True) as driver:
        driver.get(page.as_uri())
        wait_ready(driver)
        statuses = driver.execute_script(
            "return Array.from(document.querySelectorAll('.recon-status')).map(s => s.textContent)"
        )
        ready_ms = driver.execute_script("return window.reconViewersReadyMs")
        first = driver.execute_script(
            "return window.reconViewers['3dgs'].scene.cameras[0]"
        )  # the view opens at the first camera: a held-out one
        seen = snapshot(driver, "3dgs", 0)
        mesh = snapshot(driver, "plenoxel", 0)
        errors = console_errors(driver)
    assert errors == [], errors
    assert all("unavailable" not in s for s in statuses), statuses
    assert ready_ms < 3000, ready_ms
    assert first["split"] == "test"
    render = ws / "runs" / "3dgs" / "renders" / "test" / "rgb" / f"{first['name']}.png"
    expected = np.asarray(Image.open(render).convert("RGB"), np.float32) / 255
    assert seen.shape == expected.shape
    assert float(psnr(seen, expected)) >= 30.0
    # the plenoxel run shows its mesh: the sphere's pixels differ from the white background
    background = np.all(mesh > 0.99, axis=-1)
    assert 0.1 < 1 - background.mean() < 0.9


def test_recon_view_serves_a_runs_page(evaluated):
    proc = subprocess.Popen(
        [sys.executable, "-m", "recon.cli", "view", "-w", str(evaluated), "--run", "3dgs",
         "--port", "0", "--no-browser"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        line = proc.stdout.readline()
        assert line.startswith("view: http://127.0.0.1:"), (line, proc.stderr.read())
        url = line.split()[1]
        assert url.endswith("/viewer/3dgs.html")
        with urllib.request.urlopen(url, timeout=10) as r:
            page = r.read().decode()
        assert 'src="3dgs.js"' in page and 'data-root="../"' in page
        with urllib.request.urlopen(url.replace("3dgs.html", "3dgs.js"), timeout=10) as r:
            assert r.read().startswith(b"window.RECON_VIEWS")
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_recon_view_without_a_report_says_what_to_run(tmp_path):
    data = write_sphere_dataset(tmp_path / "sphere", n_train=4, n_test=1, size=16)
    ws = tmp_path / "ws"
    recon_cli("sfm", "--from-transforms", str(data), "-w", str(ws))
    proc = recon_cli("view", "-w", str(ws), "--no-browser", check=False)
    assert proc.returncode == 1
    assert "no report.html yet: run `recon eval" in proc.stderr
    proc = recon_cli("view", "-w", str(ws), "--run", "nope", "--no-browser", check=False)
    assert proc.returncode == 1 and "run 'nope' does not exist" in proc.stderr
