"""Atomic file and directory writes: write to a temporary sibling, then rename.

A reader therefore sees either the old file or the complete new one, never a half-written
file, even if the writer is killed or the disk fills up mid-write.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import uuid
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: Path):
    """Yield a temporary path beside `path`; on success rename it over `path`.

    The temporary name keeps the suffix so writers that dispatch on it (cv2, OpenEXR,
    trimesh) still work. On any exception the temporary file is removed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp-{uuid.uuid4().hex[:8]}{path.suffix}")
    try:
        with _naming_write_errors(path):
            yield tmp
            _fsync_file(tmp)
            os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


class WriteError(OSError):
    """An OSError of a write, with the output's path in its message."""


@contextlib.contextmanager
def _naming_write_errors(path: Path):
    """A failed write (disk full, file too large, read-only) says which output it was for:
    a bare `write()` OSError carries no file name, so the one-line CLI error would not either."""
    try:
        yield
    except OSError as e:
        if isinstance(e, WriteError) or e.filename is not None or e.errno is None:
            raise
        raise WriteError(e.errno, f"could not write {path}: {e.strerror}") from e


def _fsync_file(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def atomic_write_json(path: Path, obj) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


@contextlib.contextmanager
def atomic_dir(path: Path):
    """Build a whole directory in a temporary sibling and swap it in at the end.

    The old directory (if any) survives untouched until the new one is complete.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=path.parent))
    try:
        with _naming_write_errors(path):
            yield tmp
        if path.exists():
            trash = path.with_name(f".{path.name}.old-{uuid.uuid4().hex[:8]}")
            os.replace(path, trash)
            os.replace(tmp, path)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def save_torch(payload: dict, path: Path) -> None:
    """torch.save, atomically, streamed to the file (a checkpoint is never held twice in
    memory: 0.7 GB for a 256^3 plenoxel lattice with its Adam moments). torch's writer turns a
    failed write (a full disk) into an opaque "unexpected pos" RuntimeError: the OSError our
    own `write` saw is raised instead."""
    import torch

    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        failed: list[OSError] = []

        def write(data) -> int:
            try:
                return f.write(data)
            except OSError as e:
                failed.append(e)
                raise

        try:
            torch.save(payload, _Writer(write))
        except RuntimeError:
            if failed:
                raise failed[0] from None
            raise


class _Writer:
    """The file-like object torch.save needs: only `write` (and a no-op `flush`)."""

    def __init__(self, write):
        self.write = write

    def flush(self) -> None:
        pass
