"""Shared pieces of the hard-cases suite: a tiny posed workspace, fast training flags, and a
snapshot of a workspace's files to show a failed command left it as it was."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from tests.conftest import write_sphere_dataset

FAST_TRAIN = [
    "--method",
    "plenoxel",
    "--eval-views",
    "1",
    "--eval-every",
    "1000",
    "--set",
    "resolutions=16,32",
    "--set",
    "upsample_steps=10",
    "--set",
    "rays_per_batch=512",
    "--set",
    "occupancy_res=16",
    "--set",
    "samples_per_batch=16384",
    "--threads",
    "1",
]


def snapshot(ws: Path) -> dict[str, str]:
    """Every file in the workspace (lock files aside) -> its sha1."""
    return {
        str(p.relative_to(ws)): hashlib.sha1(p.read_bytes()).hexdigest()
        for p in sorted(ws.rglob("*"))
        if p.is_file() and ".locks" not in p.parts
    }


def assert_one_line_error(proc, *fragments: str) -> str:
    assert proc.returncode not in (0, None), proc.stdout + proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    for f in fragments:
        assert f in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def sphere_ws(tmp_path_factory) -> Path:
    """A workspace with the analytic sphere imported (6 train + 1 test views, 24 px), by the
    real `recon sfm` command run in-process (a subprocess would only add ~5 s of imports)."""
    from click.testing import CliRunner

    from recon.cli.main import cli

    root = tmp_path_factory.mktemp("hard")
    data = write_sphere_dataset(root / "sphere", n_train=6, n_test=1, size=24)
    ws = root / "ws"
    result = CliRunner().invoke(cli, ["sfm", "--from-transforms", str(data), "-w", str(ws)])
    assert result.exit_code == 0, result.output
    return ws
