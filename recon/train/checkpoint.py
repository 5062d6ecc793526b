"""Atomic, checksummed checkpoints. `index.json` lists them with their hashes, so a corrupt
or half-written file is detected and resume falls back to the previous one."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from recon.io.atomic import atomic_write_json, save_torch
from recon.workspace.hashing import hash_file

CHECKPOINT_SCHEMA_VERSION = 1  # the layout of a checkpoint file's payload


def has_checkpoint(directory: Path) -> bool:
    """Whether `directory` holds an index of checkpoints (something to resume from)."""
    return (directory / "index.json").exists()


def save_checkpoint(directory: Path, step: int, payload: dict, keep: int) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"step_{step:08d}.pt"
    save_torch({"schema_version": CHECKPOINT_SCHEMA_VERSION, **payload}, path)
    index = _read_index(directory)
    index = [e for e in index if e["file"] != path.name] + [
        {"file": path.name, "step": step, "hash": hash_file(path)}
    ]
    for old in index[:-keep] if keep > 0 else []:
        (directory / old["file"]).unlink(missing_ok=True)
    index = index[-keep:] if keep > 0 else index
    atomic_write_json(directory / "index.json", index)
    return path


def _read_index(directory: Path) -> list[dict]:
    try:
        return json.loads((directory / "index.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return []


def load_latest_checkpoint(directory: Path, log=print) -> dict | None:
    """Newest checkpoint whose hash matches the index; corrupt ones are reported and skipped."""
    for entry in reversed(_read_index(directory)):
        path = directory / entry["file"]
        if not path.exists() or hash_file(path) != entry["hash"]:
            log(
                f"checkpoint {path.name} is missing or corrupt (checksum mismatch); trying an older one"
            )
            continue
        try:
            payload = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # noqa: BLE001 - any unreadable file is treated as corrupt
            log(f"checkpoint {path.name} cannot be read ({e}); trying an older one")
            continue
        if payload.get("schema_version", 1) > CHECKPOINT_SCHEMA_VERSION:
            raise ValueError(
                f"checkpoint {path} was written by a newer recon "
                f"(schema_version {payload['schema_version']}): upgrade recon"
            )
        return payload
    return None
