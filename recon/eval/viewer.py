"""The 3D view of a run in report.html: recon's own WebGL2 viewer (`viewer.js`, beside this
file) and each run's scene as a script it reads, both written into the workspace's `viewer/`
folder so the page works from a double-click (file:// cannot fetch, but it runs scripts) and
from any static web server alike.

A run's scene: every camera (held-out ones first; the view opens at the first), the sfm
points, and the model: a 3dgs run's Gaussians as its renderer draws them (3D covariance,
opacity, SH up to the degree it reached, the per-view terms its renderer applies), any other
method's mesh from `recon mesh` when there is one. Arrays travel as base64 of little-endian
float32 / uint8 / uint32; a large run's Gaussians as recon's packed layout
(`gaussians.splat_pack`), its bytes a string of the script itself, which the page loads with
charset="x-user-defined" (one character a byte: ~1.6 % over the bytes, where base64 adds 33 %).
"""

from __future__ import annotations

import base64
import html
import json
import os
import shutil
from pathlib import Path

import numpy as np
import torch

from recon.cameras import Cameras
from recon.gaussians.projection import covariance_3d
from recon.gaussians.splat_pack import pack_splats, script_string
from recon.io.atomic import atomic_write_bytes
from recon.train.resolution import output_levels
from recon.workspace import Workspace, atomic_write_text
from recon.workspace.runs import load_run

VIEWER_JS = Path(__file__).with_name("viewer.js")
# Up to this many Gaussians travel as float32 (~240 bytes each at SH degree 3, ~320 in base64),
# drawn exactly as recon renders them; more, packed (`splat_pack`: ~15 bytes each at degree 3,
# a render within ~44 dB of the exact one on fox-real), without the footprint filter's
# per-Gaussian intervals.
EXACT_GAUSSIANS = 60_000
MAX_GAUSSIANS = 600_000  # the most visible (opacity times volume) of a run that has more
MAX_POINTS = 100_000  # sfm points shown (an even subsample of more)
MAX_FACES = 300_000  # mesh faces shown (a mesh with more is left out, with a note)
# The scene scripts' layout, in every doc: a viewer.js reads the scenes of its own format (3:
# large runs packed, `splat_pack`; sfm points as 16-bit fractions of their box); a scene of
# another is written again before it is shown
SCENE_FORMAT = 3


def b64(array: np.ndarray, dtype) -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).tobytes()).decode("ascii")


def camera_entry(camera: Cameras, name: str, split: str, image: str = "") -> dict:
    """One camera (`Cameras` of length 1) as the viewer takes it: cam_from_world row-major
    (16,), intrinsics in pixels, its centre, and the photo's href (or "")."""
    cam = camera.to(dtype=torch.float64)
    K = cam.K[0]
    return {
        "name": name,
        "split": split,
        "width": int(cam.width[0]),
        "height": int(cam.height[0]),
        "fx": float(K[0, 0]),
        "fy": float(K[1, 1]),
        "cx": float(K[0, 2]),
        "cy": float(K[1, 2]),
        "cam_from_world": [float(f"{x:.9g}") for x in cam.cam_from_world[0].reshape(-1).tolist()],
        "centre": [float(f"{x:.9g}") for x in cam.world_from_cam[0, :3, 3].tolist()],
        "image": image,
    }


def camera_entries(ws: Workspace, scene, level: int, page_dir: Path) -> list[dict]:
    """Held-out cameras first, then training ones, at pyramid level `level` (the size the run
    renders at), with their photos relative to the page."""
    order = scene.split("test") + scene.split("val") + scene.split("train")
    cams = scene.cameras(order, downscale=level)
    out = []
    for n, i in enumerate(order):
        frame = scene.frames[i]
        photo = ws.root / frame["image"]
        href = Path(os.path.relpath(photo, page_dir)).as_posix() if photo.exists() else ""
        out.append(camera_entry(cams[n], frame["name"], frame["split"], href))
    return out


def splat_entry(splats: dict, terms: dict, exact_max: int = EXACT_GAUSSIANS) -> dict:
    """Gaussians in `Model.splats()`'s form, drawn as `terms` (`Model.splat_rendering`) say:
    up to `exact_max` as float32 means, upper triangles of the 3D covariances, opacities, SH up
    to the degree reached and the footprint filter's sampling intervals; more, compressed
    (`splat_formats.compress_splats`)."""
    g = splats
    count = len(g["means"])
    keep = np.arange(count)
    if count > MAX_GAUSSIANS:  # the most visible: opacity times volume
        opacity = 1 / (1 + np.exp(-g["opacity_logits"].astype(np.float64)))
        weight = opacity * np.exp(g["log_scales"].astype(np.float64).sum(1))
        keep = np.sort(np.argsort(-weight, kind="stable")[:MAX_GAUSSIANS])
    degree = terms["sh_degree"]
    k = (degree + 1) ** 2
    entry = {
        "count": len(keep),
        "of": int(count),
        "sh_bases": k,
        "sh_degree": degree,
        "antialiased": bool(terms["antialiased"]),
    }
    if len(keep) > exact_max:
        header, data = pack_splats(
            g["means"][keep], g["quats"][keep], g["log_scales"][keep],
            g["opacity_logits"][keep], g["sh"][keep, :k],
        )  # fmt: skip
        # the bytes leave the JSON: `write_scene_script` writes them as a string of their own
        entry.update(encoding="pack", **header, bytes_length=len(data), bytes=data)
        return entry
    cov = covariance_3d(
        torch.from_numpy(g["quats"][keep]).double(),
        torch.from_numpy(g["log_scales"][keep]).double(),
    ).numpy()
    upper = cov[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]  # xx xy xz yy yz zz
    entry.update(
        encoding="float32",
        means=b64(g["means"][keep], "<f4"),
        cov=b64(upper, "<f4"),
        opacity=b64(1 / (1 + np.exp(-g["opacity_logits"][keep].astype(np.float64))), "<f4"),
        sh=b64(g["sh"][keep, :k], "<f4"),
    )
    if terms.get("intervals") is not None:
        entry["intervals"] = b64(terms["intervals"][keep], "<f4")
    return entry


def points_entry(scene) -> dict | None:
    points, colors = scene.info.points, scene.info.point_colors
    if points is None or len(points) == 0:
        return None
    p = points.numpy()
    c = (  # colours in [0, 1] -> bytes
        np.clip(np.asarray(colors, np.float64) * 255 + 0.5, 0, 255).astype(np.uint8)
        if colors is not None
        else np.full(p.shape, 200, np.uint8)
    )
    step = max(1, len(p) // MAX_POINTS)
    p, c = p[::step].astype(np.float64), c[::step]
    lo, hi = p.min(0), p.max(0)  # positions as 16-bit fractions of their box
    t = (p - lo) / np.where(hi > lo, hi - lo, 1.0)
    xyz16 = np.clip(np.floor(t * 65535 + 0.5), 0, 65535)
    return {"xyz16": b64(xyz16, "<u2"), "lo": lo.tolist(), "hi": hi.tolist(), "rgb": b64(c, "u1")}


def mesh_entry(path: Path, scene) -> dict | None:
    """The mesh at `path` (original units: `recon mesh`, `recon mvs`) in the normalized frame,
    with vertex colours (grey where it has none); None when it is missing, empty or larger
    than MAX_FACES."""
    import trimesh

    if not path.exists():
        return None
    mesh = trimesh.load(str(path), process=False, force="mesh")
    faces = np.asarray(mesh.faces)
    if len(faces) == 0 or len(faces) > MAX_FACES:
        return None
    xyz = scene.scene_from_world.apply(np.asarray(mesh.vertices, np.float64))
    colors = getattr(mesh.visual, "vertex_colors", None)
    rgb = (
        np.asarray(colors)[:, :3]
        if colors is not None and len(colors) == len(xyz)
        else np.full((len(xyz), 3), 180, np.uint8)
    )
    return {"xyz": b64(xyz, "<f4"), "rgb": b64(rgb, "u1"), "faces": b64(faces, "<u4")}


def run_mesh(ws: Workspace, run: str) -> Path:
    """The run's mesh from `recon mesh` (PLY, GLB or OBJ; the PLY's path when there is none)."""
    paths = [ws.mesh_dir(run) / f"mesh.{ext}" for ext in ("ply", "glb", "obj")]
    return next((p for p in paths if p.exists()), paths[0])


def viewer_scene(ws: Workspace, run: str, page_dir: Path) -> dict:
    """Everything the viewer draws for `run` (see the module docstring)."""
    model, scene, run_doc = load_run(ws, run, "cpu")
    level = output_levels(scene, run_doc)[1]
    doc = {
        "format": SCENE_FORMAT,
        "run": run,
        "method": run_doc.get("method", ""),
        "cameras": camera_entries(ws, scene, level, page_dir),
        "points": points_entry(scene),
        "background": [float(x) for x in scene.info.background],
        "near": 0.01,
        "far": float(scene.info.far) if np.isfinite(scene.info.far) else 100.0,
        "centre": scene.info.aabb.double().mean(0).tolist(),
        "frustum_size": 0.05 * float((scene.info.aabb[1] - scene.info.aabb[0]).norm()),
    }
    if model.exports_splats:
        terms = model.splat_rendering()
        doc["splats"] = splat_entry(model.splats(), terms)
        doc["background"], doc["near"] = terms["background"], terms["near"]
    else:
        doc["mesh"] = mesh_entry(run_mesh(ws, run), scene)
    doc["mvs_mesh"] = mesh_entry(ws.mvs_mesh, scene)  # `recon mvs`'s, shown on request
    return doc


def write_scene_script(folder: Path, name: str, doc: dict) -> Path:
    """folder/viewer.js (the viewer) and folder/<name>.js (the scene `doc`; packed Gaussians'
    bytes as a string after it, `splat_pack.script_string`) -> the latter."""
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(VIEWER_JS, folder / "viewer.js")
    splats = doc.get("splats") or {}
    data = splats.get("bytes")
    if data is not None:
        doc = {**doc, "splats": {k: v for k, v in splats.items() if k != "bytes"}}
    key = json.dumps(name)
    text = (
        "window.RECON_VIEWS = window.RECON_VIEWS || {};\n"
        f"window.RECON_VIEWS[{key}] = {json.dumps(doc, separators=(',', ':'))};\n"
    ).encode("ascii")
    if data is not None:
        text += f'window.RECON_VIEWS[{key}].splats.bytes = "'.encode("ascii")
        text += script_string(data) + b'";\n'
    script = folder / f"{name}.js"
    atomic_write_bytes(script, text)
    return script


def viewer_html(name: str, scene_src: str, root: str = "") -> str:
    """The block a page shows the scene `name` in (its script at `scene_src`; the photos'
    hrefs, relative to the workspace, prefixed with `root`); the page loads viewer.js once,
    after every block."""
    label = html.escape(name)
    return (
        f'<div class="recon-viewer" data-view="{label}" data-root="{html.escape(root)}" '
        f'data-src="{html.escape(scene_src)}">'
        '<div class="bar">'
        '<select class="recon-cameras" title="fly to a camera"></select> '
        '<button class="recon-reset">Reset</button> '
        '<label><input type="checkbox" class="recon-show-cameras"> cameras</label> '
        '<label><input type="checkbox" class="recon-show-points"> sfm points</label> '
        '<label class="recon-mvs"><input type="checkbox" class="recon-show-mvs"> mvs mesh</label> '
        '<span class="recon-label"></span> <span class="recon-status">loading the 3D view…</span>'
        '</div><canvas></canvas><img class="recon-photo" alt="the camera\'s photo"></div>'
        f'<script src="{html.escape(scene_src)}" charset="x-user-defined"></script>'
    )


PAGE_STYLE = (
    "body { font-family: system-ui, sans-serif; margin: 1em; background: #111; color: #ddd; }"
    " canvas { max-width: 100%; border: 1px solid #444; cursor: grab; touch-action: none; }"
    " .recon-photo { width: 320px; vertical-align: top; margin-left: 8px; }"
)


def write_page(
    folder: Path, name: str, doc: dict, page: str = "index.html", root: str = ""
) -> Path:
    """A page of its own for the scene `doc`: folder/`page` beside its scripts (`root`: the
    workspace relative to the page, for the photos)."""
    script = write_scene_script(folder, name, doc)
    path = folder / page
    atomic_write_text(
        path,
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>recon: {html.escape(name)}</title><style>{PAGE_STYLE}</style></head><body>"
        f'{viewer_html(name, script.name, root)}<script src="viewer.js"></script></body></html>\n',
    )
    return path


def write_viewer(ws: Workspace, run: str) -> Path:
    """viewer/viewer.js and viewer/<run>.js beside report.html -> the scene script's path."""
    folder = ws.report_html.parent / "viewer"
    return write_scene_script(folder, run, viewer_scene(ws, run, ws.report_html.parent))


def scene_doc(script: Path) -> dict | None:
    """The scene doc a scene script holds (without packed bytes), or None when unreadable."""
    try:
        with open(script, "rb") as f:
            f.readline()
            line = f.readline().decode("ascii")
        return json.loads(line.split(" = ", 1)[1].rstrip().rstrip(";"))
    except (OSError, ValueError, IndexError):
        return None


def scene_is_current(script: Path) -> bool:
    """The scene script exists and is of this viewer's format (`SCENE_FORMAT`)."""
    return script.exists() and (scene_doc(script) or {}).get("format") == SCENE_FORMAT


def run_page(ws: Workspace, run: str) -> Path:
    """WS/viewer/<run>.html, the run's 3D view on a page of its own (`recon view --run`); its
    scene is written again when the model is newer than it or it is of another format."""
    folder = ws.report_html.parent / "viewer"
    script = folder / f"{run}.js"
    model = ws.model_path(run)
    page = folder / f"{run}.html"
    if not model.exists():  # load_run says why (no such run, or not trained yet)
        load_run(ws, run, "cpu")
    fresh = script.exists() and script.stat().st_mtime >= model.stat().st_mtime
    if fresh and page.exists() and scene_is_current(script):
        shutil.copyfile(VIEWER_JS, folder / "viewer.js")  # this recon's viewer, whatever wrote it
        return page
    doc = viewer_scene(ws, run, ws.report_html.parent)
    return write_page(folder, run, doc, page=f"{run}.html", root="../")
