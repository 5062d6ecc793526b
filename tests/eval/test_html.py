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
