"""`workspace.json`, stage records, staleness, locks, and every path inside a workspace.

Layout:
    WS/workspace.json          schema_version + one record per stage output
    WS/images/                 undistorted training images (PNG, composited on the background)
    WS/images_<K>/             the same images area-downsampled by K (built on first use, shared)
    WS/sfm/                    sparse/ (COLMAP binary model), cameras.json, points.ply, report.json
    WS/sfm/frames/             frames taken from input videos (only for video input)
    WS/runs/<run>/             run.json, log.jsonl, checkpoints/, renders/, mesh/, eval/
    WS/report.md, WS/speed_vs_error.png
"""

from __future__ import annotations

import contextlib
import datetime as dt
import errno
import fcntl
import json
import os
import platform
import shutil
import sys
import time
from dataclasses import asdict, is_dataclass
from pathlib import Path

import recon
from recon.io.atomic import atomic_write_json
from recon.workspace.hashing import hash_tree

SCHEMA_VERSION = 1
RUN_SCHEMA_VERSION = 1  # the layout of runs/RUN/run.json
MVS_RESULT = "mvs"  # the name `recon eval` gives WS/mvs/'s mesh, beside the runs (not a run name)

# Migrations from older schemas: MIGRATIONS[v] turns a version-v document into version v+1.
MIGRATIONS: dict[int, callable] = {}


class WorkspaceError(Exception):
    """A problem with the workspace the user can fix; the CLI prints it as one line."""


def now_iso() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


def software_versions() -> dict:
    """Versions that can change a result, recorded with every stage."""
    import torch

    out = {
        "recon": recon.__version__,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
    }
    if "numba" in sys.modules:
        out["numba"] = sys.modules["numba"].__version__
        out["numba_threads"] = sys.modules["numba"].get_num_threads()
    with contextlib.suppress(Exception):
        import importlib.metadata as md

        out["pycolmap"] = md.version("pycolmap")
    return out


class Workspace:
    """A recon workspace directory. Construct with `Workspace.open` or `Workspace.create`."""

    def __init__(self, root: Path):
        self.root = Path(root)

    # ---- opening -------------------------------------------------------------------------
    @classmethod
    def create(cls, root: Path) -> Workspace:
        """Open `root`, creating an empty workspace there if it does not exist yet."""
        root = Path(root)
        if root.exists() and not root.is_dir():
            raise WorkspaceError(f"{root} exists and is not a directory")
        ws = cls(root)
        if ws.json_path.exists():
            ws.load()  # validates the schema
            return ws
        if root.exists() and any(p for p in root.iterdir() if not p.name.startswith(".")):
            raise WorkspaceError(f"{root} is a non-empty directory without workspace.json")
        root.mkdir(parents=True, exist_ok=True)
        atomic_write_json(
            ws.json_path, {"schema_version": SCHEMA_VERSION, "created": now_iso(), "stages": {}}
        )
        return ws

    @classmethod
    def open(cls, root: Path) -> Workspace:
        ws = cls(root)
        if not ws.json_path.exists():
            raise WorkspaceError(
                f"{root} is not a recon workspace (no workspace.json): run `recon sfm` first"
            )
        ws.load()
        return ws

    JSON_NAME = "workspace.json"  # the file that makes a directory a workspace
    # names inside WS/sfm/, also used while the sfm stage writes them into its staging copy
    SFM_CAMERAS, SFM_POINTS, SFM_REPORT = "cameras.json", "points.ply", "report.json"
    SFM_SPARSE, SFM_FRAMES = "sparse", "frames"

    @property
    def json_path(self) -> Path:
        return self.root / self.JSON_NAME

    def load(self) -> dict:
        try:
            doc = json.loads(self.json_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise WorkspaceError(
                f"{self.json_path} is corrupt ({e.__class__.__name__}: {e})"
            ) from e
        version = doc.get("schema_version") if isinstance(doc, dict) else None
        if not isinstance(version, int):
            raise WorkspaceError(f"{self.json_path} has no integer schema_version")
        if version > SCHEMA_VERSION:
            raise WorkspaceError(
                f"workspace schema_version {version} is newer than this recon supports "
                f"({SCHEMA_VERSION}): upgrade recon"
            )
        while version < SCHEMA_VERSION:
            doc = MIGRATIONS[version](doc)
            version = doc["schema_version"]
        doc.setdefault("stages", {})
        return doc

    # ---- paths (the only place that knows them) --------------------------------------------
    @property
    def images_dir(self) -> Path:
        return self.root / "images"

    def pyramid_dir(self, downscale: int) -> Path:
        """Level `downscale` of the image pyramid: `images/` itself for 1, else `images_<K>/`
        (the layout nerfstudio and COLMAP users know)."""
        return self.images_dir if downscale == 1 else self.root / f"images_{downscale}"

    def level_image(self, recorded: str, downscale: int) -> Path:
        """A frame's image (as recorded in cameras.json, relative to the root) at a pyramid level."""
        path = self.resolve(recorded)
        if downscale == 1:
            return path
        return self.pyramid_dir(downscale) / path.relative_to(self.images_dir)

    @property
    def sfm_dir(self) -> Path:
        return self.root / "sfm"

    @property
    def frames_dir(self) -> Path:
        """Frames taken from the input video(s), as `<video stem>_<frame index>.png`."""
        return self.sfm_dir / self.SFM_FRAMES

    @property
    def cameras_json(self) -> Path:
        return self.sfm_dir / self.SFM_CAMERAS

    @property
    def sparse_dir(self) -> Path:
        return self.sfm_dir / self.SFM_SPARSE

    @property
    def points_ply(self) -> Path:
        return self.sfm_dir / self.SFM_POINTS

    @property
    def sfm_report(self) -> Path:
        return self.sfm_dir / self.SFM_REPORT

    # WS/mvs/: dense depth maps, fused points and their mesh (`recon mvs`)
    MVS_JSON, MVS_POINTS, MVS_DEPTH = "mvs.json", "points.ply", "depth"

    @property
    def mvs_dir(self) -> Path:
        return self.root / "mvs"

    @property
    def mvs_json(self) -> Path:
        return self.mvs_dir / self.MVS_JSON

    @property
    def mvs_mesh(self) -> Path:
        return self.mvs_dir / "mesh.ply"

    @property
    def mvs_metrics_json(self) -> Path:
        return self.mvs_dir / "metrics.json"

    @property
    def runs_dir(self) -> Path:
        return self.root / "runs"

    def run_dir(self, run: str) -> Path:
        return self.runs_dir / run

    def run_json(self, run: str) -> Path:
        return self.run_dir(run) / "run.json"

    def model_path(self, run: str) -> Path:
        """The finished model of a run (`models.registry.save_model`)."""
        return self.run_dir(run) / "model.pt"

    def log_jsonl(self, run: str) -> Path:
        return self.run_dir(run) / "log.jsonl"

    def checkpoints_dir(self, run: str) -> Path:
        return self.run_dir(run) / "checkpoints"

    def renders_dir(self, run: str, name: str) -> Path:
        return self.run_dir(run) / "renders" / name

    def render_json(self, run: str, name: str) -> Path:
        return self.renders_dir(run, name) / "render.json"

    def render_video(self, run: str, name: str) -> Path:
        return self.renders_dir(run, name) / "video.mp4"

    def mesh_dir(self, run: str) -> Path:
        return self.run_dir(run) / "mesh"

    def mesh_json(self, run: str) -> Path:
        return self.mesh_dir(run) / "mesh.json"

    def export_dir(self, run: str) -> Path:
        return self.run_dir(run) / "export"

    def splat_ply(self, run: str) -> Path:
        return self.export_dir(run) / "splat.ply"

    def eval_dir(self, run: str) -> Path:
        return self.run_dir(run) / "eval"

    def metrics_json(self, run: str) -> Path:
        return self.eval_dir(run) / "metrics.json"

    @property
    def pose_accuracy_json(self) -> Path:
        return self.sfm_dir / "pose_accuracy.json"

    @property
    def report_md(self) -> Path:
        return self.root / "report.md"

    @property
    def report_html(self) -> Path:
        return self.root / "report.html"

    @property
    def sfm_plot(self) -> Path:
        return self.root / "sfm_cameras.png"

    @property
    def speed_plot(self) -> Path:
        return self.root / "speed_vs_error.png"

    def runs(self) -> list[str]:
        if not self.runs_dir.exists():
            return []
        return sorted(
            p.name
            for p in self.runs_dir.iterdir()
            if (p / "run.json").exists() and not p.name.startswith(".")
        )

    def rel(self, path: Path) -> str:
        """A path as recorded in workspace.json: relative to the root when inside it."""
        path = Path(path).resolve()
        try:
            return str(path.relative_to(self.root.resolve()))
        except ValueError:
            return str(path)

    def resolve(self, recorded: str) -> Path:
        p = Path(recorded)
        return p if p.is_absolute() else self.root / p

    # ---- locks -----------------------------------------------------------------------------
    @contextlib.contextmanager
    def writer_lock(self, scope: str, wait: bool = False):
        """Exclusive lock for one writer of `scope` ("sfm", "run-<name>"); fails fast unless
        `wait` (a shared cache such as a pyramid level, which the second writer then reuses).

        flock is released by the kernel when the process dies, so a killed writer never
        leaves a stale lock behind.
        """
        lock_dir = self.root / ".locks"
        lock_dir.mkdir(parents=True, exist_ok=True)
        f = open(lock_dir / f"{scope}.lock", "a+")  # noqa: SIM115 (held until release)
        try:
            fcntl.flock(f, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except OSError as e:
            f.close()
            if e.errno in (errno.EAGAIN, errno.EACCES):
                raise WorkspaceError(
                    f"another recon process is writing '{scope}' in {self.root}; wait for it to finish"
                ) from e
            raise
        try:
            f.seek(0), f.truncate(), f.write(f"{os.getpid()}\n"), f.flush()
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)
            f.close()

    @contextlib.contextmanager
    def _json_lock(self):
        lock_dir = self.root / ".locks"
        lock_dir.mkdir(parents=True, exist_ok=True)
        with open(lock_dir / "workspace.json.lock", "a+") as f:
            fcntl.flock(f, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(f, fcntl.LOCK_UN)

    # ---- stage records ---------------------------------------------------------------------
    def record_stage(
        self,
        key: str,
        *,
        config,
        inputs: dict[str, Path],
        outputs: dict[str, Path],
        upstream: list[str],
        started: float,
        ended: float,
        extra: dict | None = None,
    ) -> dict:
        """Write the record of a finished stage: config, input/output content hashes, versions
        and timing. `inputs`/`outputs` map a label to a path (file or folder)."""
        if is_dataclass(config):
            config = asdict(config)
        record = {
            "config": config,
            "inputs": {self.rel(p): hash_tree(p) for p in inputs.values()},
            "outputs": {self.rel(p): hash_tree(p) for p in outputs.values()},
            "upstream": upstream,
            "versions": software_versions(),
            "started": dt.datetime.fromtimestamp(started, dt.UTC).isoformat(timespec="seconds"),
            "ended": dt.datetime.fromtimestamp(ended, dt.UTC).isoformat(timespec="seconds"),
            "duration_s": round(ended - started, 3),
        }
        if extra:
            record.update(extra)
        with self._json_lock():
            doc = self.load()
            doc["stages"][key] = record
            # a rerun upstream invalidates nothing by itself; staleness is computed from hashes
            atomic_write_json(self.json_path, doc)
        return record

    def forget_stage(self, prefix: str) -> dict:
        """Drop the records of stage `prefix` and its sub-stages; returns what was dropped."""
        with self._json_lock():
            doc = self.load()
            dropped = {
                k: v for k, v in doc["stages"].items() if k == prefix or k.startswith(prefix + "/")
            }
            doc["stages"] = {k: v for k, v in doc["stages"].items() if k not in dropped}
            atomic_write_json(self.json_path, doc)
        return dropped

    def _restore_stages(self, records: dict) -> None:
        with self._json_lock():
            doc = self.load()
            doc["stages"].update(records)
            atomic_write_json(self.json_path, doc)

    @contextlib.contextmanager
    def replacing_run(self, run: str):
        """`--force` over an existing run: the old run is moved aside (records forgotten) while
        the block builds the new one, deleted when the block ends or is interrupted (Ctrl-C
        leaves a resumable new run), and put back, records included, when the block fails: a
        failed rerun loses nothing."""
        rd, aside = self.run_dir(run), self.runs_dir / f".replaced-{run}"
        shutil.rmtree(aside, ignore_errors=True)
        rd.rename(aside)
        records = self.forget_stage(f"train/{run}")
        try:
            yield
        except Exception:
            shutil.rmtree(rd, ignore_errors=True)
            aside.rename(rd)
            self._restore_stages(records)
            raise
        finally:
            shutil.rmtree(aside, ignore_errors=True)

    def stage(self, key: str) -> dict | None:
        return self.load()["stages"].get(key)

    def status(self) -> dict[str, dict]:
        """Every recorded stage with `state` = done | stale (and `why`) | missing-output."""
        stages = self.load()["stages"]
        result: dict[str, dict] = {}

        def state_of(key: str) -> tuple[str, str]:
            if key in result:
                return result[key]["state"], result[key]["why"]
            rec = stages.get(key)
            if rec is None:
                return "missing", f"{key} was never run"
            for label, digest in rec["outputs"].items():
                if not self.resolve(label).exists():
                    return "missing", f"output {label} is gone"
            for label, digest in rec["inputs"].items():
                p = self.resolve(label)
                if not p.exists():
                    return "stale", f"input {label} is gone"
                if hash_tree(p) != digest:
                    return "stale", f"input {label} changed"
            for up in rec.get("upstream", []):
                s, _ = state_of(up)
                if s != "done":
                    return "stale", f"upstream {up} is {s}"
            return "done", ""

        for key in sorted(stages, key=lambda k: stages[k].get("started", "")):
            s, why = state_of(key)
            result[key] = {**stages[key], "state": s, "why": why}
        return result

    def require_fresh(self, key: str, force: bool) -> None:
        """Refuse to build on a stage that is missing or stale, unless forced."""
        st = self.status().get(key)
        if st is None:
            raise WorkspaceError(f"stage '{key}' has not been run in {self.root}")
        if st["state"] != "done" and not force:
            raise WorkspaceError(
                f"stage '{key}' is {st['state']} ({st['why']}): rerun it, or pass --force"
            )


def timer() -> float:
    return time.time()
