"""pipelines/bench_mesh.py's F-score-against-time report: the table and the plot from given
points (no training here: the benchmark itself runs in `make bench`)."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "pipelines"))
import bench_mesh


def _points():
    return {
        "scene": "sample",
        "date": "2026-11-24T17:00:00+00:00",
        "load_average": [0.5, 0.6, 0.7],
        "points": [
            {"method": m, "budget_s": b, "steps": s, "mesher": "tsdf", "faces": 1000,
             "chamfer": c, "fscore": f, "test_psnr": 25.0}
            for m, b, s, c, f in (
                ("sdf", 60.0, 250, 0.05, 0.41), ("sdf", 600.0, 2400, 0.011, 0.905),
                ("3dgs", 60.0, 900, 0.01, 0.95),
            )
        ],
    }  # fmt: skip


def test_curve_table_has_one_row_per_run_in_order():
    md = bench_mesh.curve_markdown(_points())
    rows = [line for line in md.splitlines() if line.startswith(("| sdf", "| 3dgs"))]
    assert rows == [
        "| sdf | 60 | 250 | tsdf | 1000 | 0.0500 | 0.410 | 25.00 |",
        "| sdf | 600 | 2400 | tsdf | 1000 | 0.0110 | 0.905 | 25.00 |",
        "| 3dgs | 60 | 900 | tsdf | 1000 | 0.0100 | 0.950 | 25.00 |",
    ]
    assert "[0.5, 0.6, 0.7]" in md and "mesh_curve_sample.png" in md


def test_curve_plot_is_written(tmp_path):
    path = tmp_path / "curve.png"
    bench_mesh.plot_curve(_points(), path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 5000


def test_scene_table_has_size_picture_and_the_mvs_row(tmp_path):
    mesh = tmp_path / "mesh" / "mesh.ply"
    mesh.parent.mkdir()
    mesh.write_bytes(b"x" * 2_500_000)
    (mesh.parent / "preview_0.png").write_bytes(b"png")
    kept = bench_mesh.keep_picture(str(mesh), tmp_path / "pics" / "walnut_mvs_tsdf.png")
    assert kept == {"mesh_mb": 2.5, "picture": "walnut_mvs_tsdf.png"}
    assert (tmp_path / "pics" / "walnut_mvs_tsdf.png").read_bytes() == b"png"
    res = {
        "scene": "walnut",
        "date": "2026-11-27T12:00:00+00:00",
        "budget_s": 900.0,
        "load_average": [0.5, 0.6, 0.7],
        "training": {"mvs": {"steps": "–"}},
        "rows": [
            {"run": "mvs", "mesher": "tsdf", "faces": 10, **kept, "chamfer": 0.0005,
             "accuracy": 0.0003, "completeness": 0.0007, "precision": 0.97, "recall": 0.76,
             "fscore": 0.855, "tau": 0.0007}
        ],
    }  # fmt: skip
    row = [ln for ln in bench_mesh.markdown(res).splitlines() if ln.startswith("| mvs")]
    want = (
        "| mvs | tsdf | – | 10 | 2.5 | 0.0005 | 0.0003 | 0.0007 | 0.970 | 0.760 | 0.855 | – | – "
        "| – | [png](mesh_previews/walnut_mvs_tsdf.png) |"
    )
    assert row == [want]
