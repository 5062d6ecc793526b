import json
import multiprocessing as mp
import os

import pytest

from recon.workspace import SCHEMA_VERSION, Workspace, WorkspaceError, atomic_dir, atomic_path
from recon.workspace import workspace as wsmod


def test_create_and_reopen(tmp_path):
    ws = Workspace.create(tmp_path / "ws")
    doc = json.loads(ws.json_path.read_text())
    assert doc["schema_version"] == SCHEMA_VERSION and doc["stages"] == {}
    assert Workspace.open(tmp_path / "ws").root == ws.root


def test_open_missing_workspace_is_a_clear_error(tmp_path):
    with pytest.raises(WorkspaceError, match="not a recon workspace"):
        Workspace.open(tmp_path / "nope")


def test_newer_schema_is_refused(tmp_path):
    ws = Workspace.create(tmp_path / "ws")
    ws.json_path.write_text(json.dumps({"schema_version": SCHEMA_VERSION + 1, "stages": {}}))
    with pytest.raises(WorkspaceError, match="newer"):
        Workspace.open(ws.root)


def test_corrupt_workspace_json_is_reported(tmp_path):
    ws = Workspace.create(tmp_path / "ws")
    ws.json_path.write_text("{not json")
    with pytest.raises(WorkspaceError, match="corrupt"):
        Workspace.open(ws.root)


def test_older_schema_is_migrated(tmp_path, monkeypatch):
    ws = Workspace.create(tmp_path / "ws")
    ws.json_path.write_text(json.dumps({"schema_version": 0, "records": {"sfm": {}}}))
    monkeypatch.setitem(
        wsmod.MIGRATIONS, 0, lambda d: {"schema_version": 1, "stages": d["records"]}
    )
    assert ws.load() == {"schema_version": 1, "stages": {"sfm": {}}}


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half-writ")
        raise RuntimeError("disk full")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_atomic_dir_swaps_only_on_success(tmp_path):
    d = tmp_path / "sfm"
    d.mkdir()
    (d / "a").write_text("old")
    with pytest.raises(RuntimeError), atomic_dir(d) as tmp:
        (tmp / "a").write_text("new")
        raise RuntimeError
    assert (d / "a").read_text() == "old"
    with atomic_dir(d) as tmp:
        (tmp / "b").write_text("new")
    assert sorted(p.name for p in d.iterdir()) == ["b"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sfm"]


def _hold_lock(root, ready, release):
    ws = Workspace.open(root)
    with ws.writer_lock("sfm"):
        ready.set()
        release.wait(10)


def test_second_writer_fails_fast(tmp_path):
    ws = Workspace.create(tmp_path / "ws")
    ctx = mp.get_context("fork")
    ready, release = ctx.Event(), ctx.Event()
    p = ctx.Process(target=_hold_lock, args=(str(ws.root), ready, release))
    p.start()
    try:
        assert ready.wait(10)
        with pytest.raises(WorkspaceError, match="another recon process"), ws.writer_lock("sfm"):
            pass
        with ws.writer_lock("run-other"):  # other scopes are independent
            pass
    finally:
        release.set()
        p.join(10)
    with ws.writer_lock("sfm"):  # released when the holder exits
        pass


def test_staleness_propagates_downstream(tmp_path):
    ws = Workspace.create(tmp_path / "ws")
    src = tmp_path / "input.txt"
    src.write_text("v1")
    out = ws.root / "sfm.txt"
    out.write_text("cams")
    model = ws.root / "model.txt"
    model.write_text("m")
    ws.record_stage(
        "sfm", config={}, inputs={"s": src}, outputs={"o": out}, upstream=[], started=0, ended=1
    )
    ws.record_stage(
        "train/a",
        config={},
        inputs={"c": out},
        outputs={"m": model},
        upstream=["sfm"],
        started=1,
        ended=2,
    )
    assert {k: v["state"] for k, v in ws.status().items()} == {"sfm": "done", "train/a": "done"}
    src.write_text("v2")
    st = ws.status()
    assert st["sfm"]["state"] == "stale" and "changed" in st["sfm"]["why"]
    assert st["train/a"]["state"] == "stale" and "upstream sfm" in st["train/a"]["why"]
    with pytest.raises(WorkspaceError, match="stale"):
        ws.require_fresh("train/a", force=False)
    ws.require_fresh("train/a", force=True)
    os.remove(model)
    assert ws.status()["train/a"]["state"] == "missing"
