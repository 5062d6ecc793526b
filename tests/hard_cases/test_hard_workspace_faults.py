"""Faults while writing a workspace: a read-only workspace directory and a disk that
fills up mid-write. Each: one clear error line, a non-zero exit, the workspace byte-for-byte as
it was and no temporary file left behind. (Missing/stale stage, newer schema, corrupt
workspace.json and corrupt checkpoints are in tests/workspace/test_workspace.py, test_cli.py and
test_interruption.py.)"""

import errno
import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from recon.io.atomic import WriteError, atomic_dir
from recon.train.checkpoint import save_checkpoint
from tests.conftest import REPO
from tests.hard_cases.conftest import FAST_TRAIN, assert_one_line_error, snapshot


def run_recon(args, limit_bytes=None, read_only=None):
    """`recon ARGS` in a subprocess; optionally with a file-size limit (writes past it fail with
    EFBIG, as on a full disk: Python ignores SIGXFSZ) or with `read_only` mounted read-only in a
    private mount namespace (root ignores permission bits, so chmod would not do)."""
    cmd = [sys.executable, "-m", "recon.cli", *args]
    if read_only is not None and os.geteuid() == 0:
        cmd = [
            "unshare",
            "-m",
            "sh",
            "-c",
            'mount --bind "$1" "$1" && mount -o remount,ro,bind "$1" && shift && exec "$@"',
            "sh",
            str(read_only),
            *cmd,
        ]

    def limit():
        if limit_bytes is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        cmd,
        check=False,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
        cwd=REPO,
        preexec_fn=limit,
    )


def no_temporaries(ws: Path) -> bool:
    return not [p for p in ws.rglob("*") if ".tmp-" in p.name or ".old-" in p.name]


def read_only_mounts_work(tmp: Path) -> bool:
    """Root (who ignores permission bits) needs a private read-only bind mount; can it mount?"""
    if os.geteuid() != 0:
        return True
    if shutil.which("unshare") is None:
        return False
    script = f'mount --bind "{tmp}" "{tmp}" && mount -o remount,ro,bind "{tmp}"'
    probe = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, check=False)
    return probe.returncode == 0


def test_read_only_workspace_is_refused_and_left_as_it_was(sphere_ws, tmp_path):
    if not read_only_mounts_work(tmp_path):
        pytest.skip(
            "running as root without mount privileges: no way to make a directory read-only"
        )
    before = snapshot(sphere_ws)
    if os.geteuid() != 0:
        for p in [sphere_ws, *sphere_ws.rglob("*")]:
            if p.is_dir():
                p.chmod(0o555)
    try:
        proc = run_recon(
            ["train", "-w", str(sphere_ws), "--run", "ro", "--steps", "5", *FAST_TRAIN],
            read_only=sphere_ws,
        )
    finally:
        for p in [sphere_ws, *sphere_ws.rglob("*")]:
            if p.is_dir():
                p.chmod(0o755)
    line = assert_one_line_error(proc)
    assert "Read-only file system" in line or "Permission denied" in line
    assert snapshot(sphere_ws) == before and not (sphere_ws / "runs" / "ro").exists()


def test_disk_full_during_train_names_the_file_and_leaves_no_run(sphere_ws):
    """The first checkpoint (~0.5 MB) cannot be written, though run.json (~2.5 kB) can: no half
    file, no half run directory."""
    before = snapshot(sphere_ws)
    proc = run_recon(
        ["train", "-w", str(sphere_ws), "--run", "full", "--steps", "5", *FAST_TRAIN],
        limit_bytes=8000,
    )
    assert_one_line_error(proc, "could not write", "step_00000000.pt", "File too large")
    assert snapshot(sphere_ws) == before and no_temporaries(sphere_ws)
    assert not (sphere_ws / "runs" / "full").exists()


def test_disk_full_during_sfm_rerun_keeps_the_old_stage(sphere_ws):
    before = snapshot(sphere_ws)
    data = sphere_ws.parent / "sphere"
    proc = run_recon(
        ["sfm", "--from-transforms", str(data), "-w", str(sphere_ws)], limit_bytes=3000
    )
    assert_one_line_error(proc, "could not write", "File too large")
    assert snapshot(sphere_ws) == before and no_temporaries(sphere_ws)


class _FillingFile:
    """A file whose writes land until `room` bytes are written, then fail with ENOSPC."""

    def __init__(self, f, room):
        self.f, self.room = f, room

    def write(self, data):
        data = bytes(data)
        if len(data) > self.room:
            self.f.write(data[: self.room])
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= len(data)
        return self.f.write(data)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()


def test_enospc_midway_through_a_checkpoint_leaves_no_partial_file(tmp_path, monkeypatch):
    """A checkpoint's file fills the disk after 1,000 bytes (torch.save streams into it)."""
    import recon.io.atomic

    ck = tmp_path / "checkpoints"
    save_checkpoint(ck, 0, {"x": torch.zeros(4)}, keep=2)
    before = sorted(p.name for p in ck.iterdir())
    index = (ck / "index.json").read_text()
    fill = lambda path, mode: _FillingFile(open(path, mode), 1000)  # noqa: SIM115 (closed by __exit__)
    monkeypatch.setattr(recon.io.atomic, "open", fill, raising=False)
    with pytest.raises(WriteError, match=r"could not write .*step_00000007\.pt: No space left"):
        save_checkpoint(ck, 7, {"x": torch.ones(1000)}, keep=2)
    assert sorted(p.name for p in ck.iterdir()) == before
    assert (ck / "index.json").read_text() == index


def test_enospc_inside_an_atomic_directory_keeps_the_old_one(tmp_path):
    d = tmp_path / "sfm"
    d.mkdir()
    (d / "cameras.json").write_text("old")
    with (
        pytest.raises(WriteError, match=r"could not write .*sfm: No space left"),
        atomic_dir(d) as tmp,
    ):
        (tmp / "points.ply").write_text("half")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert [p.name for p in tmp_path.iterdir()] == ["sfm"] and (
        d / "cameras.json"
    ).read_text() == "old"
