"""report.html: one page per workspace (no network; the pictures and scripts are files beside
it, linked by relative paths) that shows what every evaluated run looks like: the metrics
table, the speed-vs-error plot, the sfm stage (registered and unregistered photos with
reasons, reprojection error, a plot of the camera frusta over the sparse points), and per run
its interactive 3D view (`recon.eval.viewer`), each held-out view as photo | render | error
heat map | depth thumbnails that open full size, the mesh previews and the rendered videos."""

from __future__ import annotations

import datetime as dt
import html
import json
import os
from pathlib import Path

from recon.eval.report import COLUMNS, _fmt, _size, row_cells
from recon.eval.viewer import scene_is_current, viewer_html
from recon.eval.visuals import ERROR_MAX, KINDS
from recon.workspace import Workspace, atomic_write_text
from recon.workspace.workspace import MVS_RESULT

STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5em; color: #222; max-width: 1400px; }
table { border-collapse: collapse; margin: 0.5em 0 1em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 3px 7px; text-align: right; }
th { background: #f3f3f3; } td.l, th.l { text-align: left; }
.views td { text-align: center; } .views img { display: block; width: 180px; }
.warn { background: #fff3cd; border: 1px solid #e0c36c; padding: 0.5em 0.8em; }
.gallery img { margin: 0 6px 6px 0; border: 1px solid #ddd; }
.recon-viewer { margin: 0.5em 0 1.5em; } .recon-viewer canvas { max-width: 100%;
  border: 1px solid #ccc; cursor: grab; touch-action: none; background: #000; }
.recon-viewer .bar { margin: 4px 0; font-size: 0.9em; } .recon-viewer .recon-photo { width: 240px;
  vertical-align: top; margin-left: 8px; border: 1px solid #ddd; }
.legend { display: inline-block; width: 240px; height: 12px; vertical-align: middle;
  background: linear-gradient(to right, #30123b, #4686fb, #1ae4b6, #a2fc3c, #fabb39, #e4460a, #7a0403); }
"""


def esc(x) -> str:
    return html.escape(str(x))


def rel(path: Path, root: Path) -> str:
    """`path` relative to the workspace root, with forward slashes (an href)."""
    return Path(os.path.relpath(path, root)).as_posix()


def metrics_table(metrics: dict[str, dict]) -> str:
    """The report.md table, each run's name linking to its section."""
    rows = []
    for run, m in sorted(metrics.items()):
        cells = [esc(c) for c in row_cells(run, m)]
        cells[0] = f'<a href="#run-{esc(run)}">{esc(run)}</a>'
        rows.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    header = "".join(f"<th>{esc(h)}</th>" for h in COLUMNS)
    return f"<table><tr>{header}</tr>{''.join(rows)}</table>"


def sfm_section(ws: Workspace) -> str:
    """Counts, reprojection error, the partial-registration warning, the photos left out with
    their reasons, and the cameras plot (when `sfm_cameras.png` exists)."""
    if not ws.sfm_report.exists():
        return ""
    r = json.loads(ws.sfm_report.read_text())
    parts = ["<h2>Camera poses (sfm)</h2>"]
    facts = []
    if "images_registered" in r:
        facts.append(
            f"{r['images_registered']} of {r.get('images_usable', '?')} usable photos registered "
            f"({r.get('images_given', '?')} given)"
        )
    if "mean_reprojection_error_px" in r:
        facts.append(f"mean reprojection error {r['mean_reprojection_error_px']:.3f} px")
    if "images" in r:
        splits = ", ".join(f"{n} {name}" for name, n in (r.get("splits") or {}).items())
        facts.append(f"{r['images']} images in the workspace ({splits})")
    parts.append(f"<p>{esc('; '.join(facts))}.</p>")
    registration = r.get("registration", {})
    if registration.get("partial"):
        parts.append(
            f'<p class="warn">Only {registration["registered"]} of {registration["usable"]} '
            f"photos registered (below {registration['min_registered']:g}); commonest reason: "
            f"{esc(registration['commonest_reason'])} ({registration['commonest_reason_count']} photos).</p>"
        )
    if ws.cameras_json.exists():
        frames = json.loads(ws.cameras_json.read_text()).get("frames", [])
        names = ", ".join(f"{esc(f['name'])} ({esc(f['split'])})" for f in frames)
        parts.append(
            f"<details><summary>{len(frames)} registered photos</summary><p>{names}</p></details>"
        )
    left_out = [(u["name"], u["reason"]) for u in r.get("unregistered", [])]
    left_out += [(s["name"], "skipped: " + s["reason"]) for s in r.get("skipped", [])]
    if left_out:
        rows = "".join(
            f'<tr><td class="l">{esc(n)}</td><td class="l">{esc(why)}</td></tr>'
            for n, why in left_out
        )
        parts.append(
            f'<table><tr><th class="l">photo left out</th><th class="l">why</th></tr>{rows}</table>'
        )
    if ws.sfm_plot.exists():
        src = rel(ws.sfm_plot, ws.root)
        parts.append(
            f'<a href="{src}"><img src="{src}" alt="camera frusta and sparse points" width="560"></a>'
        )
    return "\n".join(parts)


def views_table(ws: Workspace, run: str, m: dict) -> str:
    pictures = m.get("pictures") or {}
    if not pictures:
        return "<p>No pictures (evaluated with --no-pictures).</p>"
    views_dir = ws.eval_dir(run) / "views"
    head = "".join(f"<th>{k}</th>" for k in ("view", "PSNR", *KINDS))
    rows = []
    for name, kinds in pictures.items():
        cells = [
            f'<td class="l">{esc(name)}</td>',
            f"<td>{_fmt(m['per_view'][name].get('psnr'))}</td>",
        ]
        for kind in KINDS:
            pic = kinds[kind]
            full, thumb = (
                rel(views_dir / pic["full"], ws.root),
                rel(views_dir / pic["thumb"], ws.root),
            )
            cells.append(
                f'<td><a href="{full}"><img src="{thumb}" alt="{esc(name)} {kind}"></a></td>'
            )
        rows.append("<tr>" + "".join(cells) + "</tr>")
    legend = (
        f'<p>Error: mean absolute RGB error per pixel, <span class="legend"></span> 0 to '
        f"{ERROR_MAX} or more. Depth: inverse depth, near red, far blue; black where the render "
        "is empty. Click a picture for full size.</p>"
    )
    return legend + f'<table class="views"><tr>{head}</tr>{"".join(rows)}</table>'


def mesh_gallery(ws: Workspace, run: str) -> str:
    if not ws.mesh_json(run).exists():
        return ""
    mesh = json.loads(ws.mesh_json(run).read_text())
    # the file as it is in this workspace: mesh.json's absolute path goes stale when the
    # workspace is moved or copied
    path = ws.mesh_dir(run) / Path(mesh["path"]).name
    text = (
        f"<h4>Mesh</h4><p>{_fmt(mesh.get('faces'))} faces, {esc(mesh.get('method', ''))}: "
        f'<a href="{rel(path, ws.root)}">{esc(path.name)}</a></p>'
    )
    return text + preview_gallery(ws, ws.mesh_dir(run), mesh.get("previews", []))


def preview_gallery(ws: Workspace, folder: Path, names: list[str]) -> str:
    """The mesh previews `names` in `folder` that exist, as linked thumbnails ("" if none)."""
    imgs = "".join(
        f'<a href="{rel(p, ws.root)}"><img src="{rel(p, ws.root)}" alt="mesh preview" width="240"></a>'
        for p in (folder / name for name in names)
        if p.exists()
    )
    return f'<div class="gallery">{imgs}</div>' if imgs else ""


def videos(ws: Workspace, run: str) -> str:
    renders = ws.run_dir(run) / "renders"
    found = sorted(renders.glob("*/video.mp4")) if renders.exists() else []
    return "".join(
        f"<h4>Video: {esc(v.parent.name)}</h4>"
        f'<video controls loop muted width="480" src="{rel(v, ws.root)}"></video>'
        for v in found
    )


def mvs_section(ws: Workspace, m: dict) -> str:
    """The mesh of `recon mvs`: its geometry scores, a link to it and its previews."""
    stage = json.loads(ws.mvs_json.read_text()) if ws.mvs_json.exists() else {}
    geo = m.get("geometry", {})
    score = (
        f"Chamfer {_fmt(geo.get('chamfer'), 5)}, F-score {_fmt(geo.get('fscore'), 3)} at "
        f"τ {_fmt(geo.get('tau'), 5)}"
        if geo.get("status") == "ok"
        else esc(geo.get("status", "not scored"))
    )
    return (
        f'<h3 id="run-{MVS_RESULT}">{MVS_RESULT} (multi-view stereo)</h3>'
        f"<p>{_fmt(stage.get('views'))} depth maps at {_size(stage.get('size'))}, "
        f"{_fmt(stage.get('faces'))} faces: "
        f'<a href="{rel(ws.mvs_mesh, ws.root)}">{esc(ws.mvs_mesh.name)}</a>; {score}.</p>'
        + preview_gallery(ws, ws.mvs_dir, stage.get("previews", []))
    )


def viewer_block(ws: Workspace, run: str) -> str:
    """The run's interactive 3D view (`recon.eval.viewer`), when its scene script exists."""
    script = ws.report_html.parent / "viewer" / f"{run}.js"
    if not script.exists():
        return ""
    if not scene_is_current(script):  # an older recon's scene
        return (
            f"<p>Its 3D view was written by another version of recon: "
            f"<code>recon eval -w WS --run {esc(run)}</code> writes it again.</p>"
        )
    return viewer_html(run, rel(script, ws.report_html.parent))


def run_section(ws: Workspace, run: str, m: dict) -> str:
    if run == MVS_RESULT:
        return mvs_section(ws, m)
    mean = m.get("mean", {})
    lp = f", LPIPS {mean['lpips']:.4f}" if "lpips" in mean else ""
    at = m.get("photo_size")
    if at:
        d, u = at["mean"], at["upsampled"]
        at_lp = lambda x: f", LPIPS {x['lpips']:.4f}" if "lpips" in x else ""
        photos = (
            f" At the photos' own size, {_size(at['resolution'])}: PSNR {_fmt(d.get('psnr'))} dB, "
            f"SSIM {_fmt(d.get('ssim'), 4)}{at_lp(d)} (the render at {_size(m.get('resolution'))} upsampled: "
            f"{_fmt(u.get('psnr'))} dB, SSIM {_fmt(u.get('ssim'), 4)}{at_lp(u)})."
        )
    else:
        photos = ""
    return (
        f'<h3 id="run-{esc(run)}">{esc(run)} ({esc(m.get("method", ""))})</h3>'
        f"<p>{m.get('views', 0)} held-out views at {_size(m.get('resolution'))}: PSNR "
        f"{_fmt(mean.get('psnr'))} dB, SSIM {_fmt(mean.get('ssim'), 4)}{lp}.{photos}</p>"
        + viewer_block(ws, run)
        + views_table(ws, run, m)
        + mesh_gallery(ws, run)
        + videos(ws, run)
    )


def write_html_report(ws: Workspace, metrics: dict[str, dict]) -> Path:
    """report.html for `metrics` (run -> metrics.json contents) -> ws.report_html."""
    speed = ""
    if ws.speed_plot.exists():
        src = rel(ws.speed_plot, ws.root)
        speed = f'<h2>Speed vs error</h2><img src="{src}" alt="speed vs error" width="640">'
    body = [
        f"<h1>recon report: {esc(ws.root.name)}</h1>",
        (
            f"<p>Written {dt.datetime.now().isoformat(timespec='seconds')}. Image metrics on "
            "the held-out views; PSNR certifies interpolation between the cameras, not geometry.</p>"
        ),
        "<h2>Runs</h2>",
        metrics_table(metrics),
        speed,
        sfm_section(ws),
        "<h2>What each run looks like</h2>",
        *(run_section(ws, run, m) for run, m in sorted(metrics.items())),
    ]
    if (ws.report_html.parent / "viewer" / "viewer.js").exists() and any(
        'class="recon-viewer"' in part for part in body
    ):
        body.append('<script src="viewer/viewer.js"></script>')
    page = (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>recon report: {esc(ws.root.name)}</title><style>{STYLE}</style></head>"
        f"<body>\n{chr(10).join(body)}\n</body></html>\n"
    )
    atomic_write_text(ws.report_html, page)
    return ws.report_html
