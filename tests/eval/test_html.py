"""report.html's pieces that read stage files: links stay inside the workspace."""

import json

from recon.eval.html import mesh_gallery
from recon.workspace import Workspace


def test_mesh_link_points_into_a_moved_workspace(tmp_path):
    ws = Workspace(tmp_path / "moved")
    mesh_dir = ws.mesh_dir("r")
    mesh_dir.mkdir(parents=True)
    (mesh_dir / "mesh.glb").write_bytes(b"glb")
    (mesh_dir / "preview_0.png").write_bytes(b"png")
    # mesh.json as written where the workspace used to be
    old = tmp_path / "elsewhere" / "runs" / "r" / "mesh" / "mesh.glb"
    doc = {"path": str(old), "faces": 12, "method": "tsdf", "previews": ["preview_0.png"]}
    ws.mesh_json("r").write_text(json.dumps(doc))
    html = mesh_gallery(ws, "r")
    assert 'href="runs/r/mesh/mesh.glb"' in html and "elsewhere" not in html
    assert 'src="runs/r/mesh/preview_0.png"' in html


def test_a_3d_view_of_another_format_is_not_shown_but_named(tmp_path):
    """A scene script an older recon wrote (another format) would not draw with this viewer:
    the report says how to write it again instead."""
    from types import SimpleNamespace

    from recon.eval.html import viewer_block
    from recon.eval.viewer import SCENE_FORMAT, write_scene_script

    ws = SimpleNamespace(report_html=tmp_path / "report.html")
    write_scene_script(tmp_path / "viewer", "new", {"format": SCENE_FORMAT, "cameras": []})
    write_scene_script(tmp_path / "viewer", "old", {"cameras": []})
    assert 'data-view="new"' in viewer_block(ws, "new")
    old = viewer_block(ws, "old")
    assert "recon-viewer" not in old and "recon eval -w WS --run old" in old
    assert viewer_block(ws, "missing") == ""
