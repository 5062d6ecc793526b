"""End-to-end CLI behaviour: help, version, sfm import, status, bad input (the entry point
`python -m recon.cli` itself in a subprocess, the rest through `recon_cli`)."""

import json
import shutil
import subprocess
import sys

import click
import pytest

from tests.conftest import SHARED_DATA, recon_cli

LEGO = SHARED_DATA / "nerf_synthetic_lego_400"


def test_help_lists_only_implemented_commands():
    out = recon_cli("--help", subprocess_=True).stdout
    for cmd in ("sfm", "status", "train", "render"):
        assert cmd in out
    assert recon_cli("--version", subprocess_=True).stdout.strip().startswith("recon, version")
    assert "--from-transforms" in recon_cli("sfm", "--help", subprocess_=True).stdout


def test_help_reads_each_commands_short_help_without_importing_it():
    from recon.cli.main import COMMANDS, cli, command_short_help

    ctx = click.Context(cli)
    for name in COMMANDS:
        for limit in (30, 45, 80):
            own = cli.get_command(ctx, name).get_short_help_str(limit)
            assert command_short_help(name, limit) == own != "", name
    # a fresh interpreter: listing the commands loads none of them (nor torch)
    probe = (
        "import sys; from click.testing import CliRunner; from recon.cli.main import cli; "
        "out = CliRunner().invoke(cli, ['--help']).output; assert 'train' in out, out; "
        "print(sorted(m for m in sys.modules if m == 'torch' or m.startswith('recon.cli.')))"
    )
    loaded = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True
    )
    assert loaded.stdout.strip() == "['recon.cli.common', 'recon.cli.main']"


def test_status_and_staleness_after_input_change(tmp_path, blender_dataset):
    ws = tmp_path / "ws"
    out = json.loads(
        recon_cli("sfm", "--from-transforms", str(blender_dataset), "-w", str(ws), "--json").stdout
    )
    assert out["splits"] == {"train": 4, "test": 2}
    st = json.loads(recon_cli("status", "-w", str(ws), "--json").stdout)
    assert [(s["stage"], s["state"]) for s in st["stages"]] == [("sfm", "done")]
    meta = json.loads((blender_dataset / "transforms_train.json").read_text())
    meta["frames"][0]["transform_matrix"][0][3] += 0.1
    (blender_dataset / "transforms_train.json").write_text(json.dumps(meta))
    st = json.loads(recon_cli("status", "-w", str(ws), "--json").stdout)
    assert st["stages"][0]["state"] == "stale"
    assert "stale" in recon_cli("status", "-w", str(ws)).stdout


def _assert_one_line_error(proc, match):
    assert proc.returncode != 0
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) <= 2 and match in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr


def test_bad_inputs_give_one_line_errors_and_leave_no_workspace(tmp_path):
    ws = tmp_path / "ws"
    _assert_one_line_error(
        recon_cli(
            "sfm", "--from-transforms", str(tmp_path / "missing"), "-w", str(ws), check=False
        ),
        "does not exist",
    )
    empty = tmp_path / "empty"
    empty.mkdir()
    _assert_one_line_error(
        recon_cli("sfm", "--from-transforms", str(empty), "-w", str(ws), check=False),
        "no transforms",
    )
    bad = tmp_path / "bad.json"
    bad.write_text("{broken")
    _assert_one_line_error(
        recon_cli("sfm", "--from-transforms", str(bad), "-w", str(ws), check=False),
        "not valid JSON",
    )
    assert not ws.exists()
    _assert_one_line_error(recon_cli("status", "-w", str(ws), check=False), "not a recon workspace")


def test_failed_rerun_leaves_workspace_as_it_was(tmp_path, blender_dataset):
    ws = tmp_path / "ws"
    recon_cli("sfm", "--from-transforms", str(blender_dataset), "-w", str(ws))
    before = {
        p.relative_to(ws): p.read_bytes()
        for p in ws.rglob("*")
        if p.is_file() and ".locks" not in p.parts
    }
    shutil.rmtree(blender_dataset / "test")  # images vanish: the rerun must fail cleanly
    _assert_one_line_error(
        recon_cli("sfm", "--from-transforms", str(blender_dataset), "-w", str(ws), check=False),
        "missing",
    )
    after = {
        p.relative_to(ws): p.read_bytes()
        for p in ws.rglob("*")
        if p.is_file() and ".locks" not in p.parts
    }
    assert after == before


def test_newer_schema_and_lock_held(tmp_path, blender_dataset):
    ws = tmp_path / "ws"
    recon_cli("sfm", "--from-transforms", str(blender_dataset), "-w", str(ws))
    doc = json.loads((ws / "workspace.json").read_text())
    (ws / "workspace.json").write_text(json.dumps({**doc, "schema_version": 99}))
    _assert_one_line_error(recon_cli("status", "-w", str(ws), check=False), "newer")
    (ws / "workspace.json").write_text(json.dumps(doc))
    import fcntl

    (ws / ".locks").mkdir(exist_ok=True)
    with open(ws / ".locks" / "sfm.lock", "a+") as f:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        _assert_one_line_error(
            recon_cli("sfm", "--from-transforms", str(blender_dataset), "-w", str(ws), check=False),
            "another recon process",
        )
    assert json.loads((ws / "workspace.json").read_text()) == doc


@pytest.mark.skipif(not LEGO.exists(), reason="../shared/data not present")
def test_lego_import_downscaled(tmp_path):
    import zlib  # noqa: F401

    import pycolmap

    ws = tmp_path / "lego"
    recon_cli("sfm", "--from-transforms", str(LEGO), "--downscale", "2", "-w", str(ws))
    rec = pycolmap.Reconstruction(str(ws / "sfm" / "sparse"))
    train = [im for im in rec.images.values() if im.name.startswith("train/")]
    assert len(train) == 100
    assert {
        (rec.cameras[im.camera_id].width, rec.cameras[im.camera_id].height) for im in train
    } == {(200, 200)}
    cams = json.loads((ws / "sfm" / "cameras.json").read_text())
    assert cams["background"] == [1.0, 1.0, 1.0] and not cams["unbounded"]
    st = json.loads(recon_cli("status", "-w", str(ws), "--json").stdout)
    assert st["stages"][0]["state"] == "done"
