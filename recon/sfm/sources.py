"""Known-pose inputs -> `PosedImages` (OpenCV `world_from_cam`, pixel intrinsics, splits).

Foreign conventions are converted here and nowhere else: transforms.json stores OpenGL
camera-to-world matrices; COLMAP stores `cam_from_world` with quaternions; LLFF's
poses_bounds.npy stores camera-to-world matrices in (down, right, back) axes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recon.cameras.conventions import opencv_c2w_from_opengl_c2w

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")


class SourceError(ValueError):
    """Malformed or missing pose input; the CLI shows it as one line."""


@dataclass
class PosedImage:
    name: str  # unique stem used for every per-view output
    path: Path
    K: np.ndarray  # (3, 3) pixels, for the image at its file size
    dist: np.ndarray | None  # OpenCV (k1, k2, p1, p2) or None for a pinhole
    world_from_cam: np.ndarray  # (4, 4) OpenCV convention
    split: str  # train | val | test
    depth_path: Path | None = (
        None  # ground-truth z-depth map (EXR, original units), if the dataset has one
    )


@dataclass
class PosedImages:
    frames: list[PosedImage]
    points: np.ndarray | None = None  # (P, 3) world
    point_colors: np.ndarray | None = None  # (P, 3) uint8
    source: str = ""
    gt_mesh: Path | None = None  # ground-truth mesh (original units), if the dataset has one
    extra: dict = field(default_factory=dict)


def _resolve_image(base: Path, file_path: str) -> Path:
    p = (base / file_path).resolve()
    if p.exists():
        return p
    for suffix in IMAGE_SUFFIXES:  # Blender files omit the extension
        q = p.with_name(p.name + suffix)
        if q.exists():
            return q
    raise SourceError(f"image {file_path} listed in transforms is missing under {base}")


def _image_size(path: Path) -> tuple[int, int]:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SourceError(f"cannot read image {path}")
    return img.shape[1], img.shape[0]


def _intrinsics(meta: dict, frame: dict, path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Per-frame keys override top-level ones (nerfstudio); Blender has only camera_angle_x."""
    get = lambda k: frame.get(k, meta.get(k))
    w, h = get("w"), get("h")
    if w is None or h is None:
        w, h = _image_size(path)
    w, h = float(w), float(h)
    if get("fl_x") is not None:
        fx = float(get("fl_x"))
        fy = float(get("fl_y") if get("fl_y") is not None else fx)
    elif get("camera_angle_x") is not None:
        fx = 0.5 * w / np.tan(0.5 * float(get("camera_angle_x")))
        fy = 0.5 * h / np.tan(0.5 * float(get("camera_angle_y"))) if get("camera_angle_y") else fx
    else:
        raise SourceError("transforms has neither fl_x nor camera_angle_x")
    cx = float(get("cx") if get("cx") is not None else w / 2)
    cy = float(get("cy") if get("cy") is not None else h / 2)
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    dist = np.array([float(get(k) or 0.0) for k in ("k1", "k2", "p1", "p2")])
    return K, (dist if np.any(dist != 0) else None)


def _read_transforms_file(path: Path, split: str | None) -> list[PosedImage]:
    try:
        meta = json.loads(path.read_text())
        frames = meta["frames"]
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SourceError(f"{path} is not valid JSON ({e})") from e
    except (KeyError, TypeError) as e:
        raise SourceError(f"{path} has no 'frames' list") from e
    if not frames:
        raise SourceError(f"{path} lists no frames")
    out = []
    for i, fr in enumerate(frames):
        try:
            c2w_gl = np.asarray(fr["transform_matrix"], dtype=np.float64)
            file_path = fr["file_path"]
        except (KeyError, TypeError) as e:
            raise SourceError(f"{path}: frame {i} lacks {e}") from e
        if c2w_gl.shape != (4, 4) or not np.all(np.isfinite(c2w_gl)):
            raise SourceError(f"{path}: frame {i} transform_matrix is not a finite 4x4 matrix")
        img_path = _resolve_image(path.parent, file_path)
        K, dist = _intrinsics(meta, fr, img_path)
        name = img_path.stem
        depth = fr.get("depth_file_path")
        depth = (path.parent / depth).resolve() if depth else None
        out.append(
            PosedImage(
                name,
                img_path,
                K,
                dist,
                opencv_c2w_from_opengl_c2w(c2w_gl),
                split or "",
                depth if depth is not None and depth.exists() else None,
            )
        )
    return out


def _gt_mesh(path: Path) -> Path | None:
    """`gt_mesh_path` (recon's key) in a transforms file: the scene's ground-truth mesh."""
    try:
        rel = json.loads(path.read_text()).get("gt_mesh_path")
    except (json.JSONDecodeError, AttributeError):
        return None
    return (path.parent / rel).resolve() if rel and (path.parent / rel).exists() else None


def holdout_split(names: list[str], every: int = 8) -> list[str]:
    """Every `every`-th image (in name order) is held out for testing, as the field does."""
    order = sorted(range(len(names)), key=lambda i: names[i])
    split = ["train"] * len(names)
    for rank, i in enumerate(order):
        if rank % every == 0:
            split[i] = "test"
    return split


def _dedupe_names(frames: list[PosedImage]) -> None:
    """Names must be unique within a split (renders go to renders/<split>/rgb/<name>.png)."""
    seen: dict[tuple[str, str], int] = {}
    for f in frames:
        key = (f.split, f.name)
        seen[key] = seen.get(key, 0) + 1
        if seen[key] > 1:
            f.name = f"{f.name}_{seen[key]}"


def read_transforms(path: Path, holdout_every: int = 8) -> PosedImages:
    """A transforms*.json file, or a folder with transforms.json or transforms_{split}.json."""
    path = Path(path)
    if not path.exists():
        raise SourceError(f"{path} does not exist")
    if path.is_dir():
        split_files = {s: path / f"transforms_{s}.json" for s in ("train", "val", "test")}
        split_files = {s: p for s, p in split_files.items() if p.exists()}
        if split_files:
            frames = [f for s, p in split_files.items() for f in _read_transforms_file(p, s)]
        elif (path / "transforms.json").exists():
            return read_transforms(path / "transforms.json", holdout_every)
        else:
            raise SourceError(f"{path} holds no transforms.json or transforms_<split>.json")
        gt_mesh = next((m for p in split_files.values() if (m := _gt_mesh(p))), None)
    else:
        frames = _read_transforms_file(path, None)
        for f, s in zip(frames, holdout_split([f.name for f in frames], holdout_every)):
            f.split = s
        gt_mesh = _gt_mesh(path)
    _dedupe_names(frames)
    return PosedImages(frames, source=str(path), gt_mesh=gt_mesh)


LLFF_IMAGE_DIRS = ("images", "images_2", "images_4", "images_8")


def opencv_c2w_from_llff(pose: np.ndarray) -> np.ndarray:
    """(3, 4) camera-to-world in LLFF's axes (x down, y right, z back; Mildenhall et al. 2019,
    "Local Light Field Fusion", the released poses_bounds.npy) -> (4, 4) OpenCV camera-to-world
    (x right, y down, z forward): columns (y, x, -z) of the rotation, the centre unchanged."""
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2] = pose[:, 1], pose[:, 0], -pose[:, 2]
    out[:3, 3] = pose[:, 3]
    return out


def read_llff(root: Path, images_dir: Path | None = None, holdout_every: int = 8) -> PosedImages:
    """An LLFF capture: `root/poses_bounds.npy`, (N, 17) rows of a flattened 3 x 5 matrix
    [camera-to-world (3, 4) | (height, width, focal)] at the photos' original size and the
    (near, far) depth bounds; the photos sorted by name in `images_dir`, else the first of
    root/images, images_2, images_4, images_8 (the release's downsampled copies). Intrinsics are
    scaled to the files' size with the principal point at the centre, as LLFF assumes; every
    `holdout_every`-th photo is held out (LLFF's protocol with 8). The bounds go in `extra`."""
    root = Path(root)
    npy = root / "poses_bounds.npy" if root.is_dir() else root
    if not npy.exists():
        raise SourceError(f"{root} holds no poses_bounds.npy")
    try:
        rows = np.load(npy, allow_pickle=False)
    except (ValueError, OSError) as e:
        raise SourceError(f"cannot read {npy}: {e}") from e
    if rows.ndim != 2 or rows.shape[1] != 17 or not np.all(np.isfinite(rows)):
        raise SourceError(f"{npy} is not an (N, 17) array of finite LLFF poses and bounds")
    base = npy.parent
    folder = images_dir or next((base / d for d in LLFF_IMAGE_DIRS if (base / d).is_dir()), None)
    if folder is None or not Path(folder).is_dir():
        raise SourceError(
            f"no images folder ({', '.join(LLFF_IMAGE_DIRS)}) beside {npy}; pass --images"
        )
    paths = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if len(paths) != len(rows):
        raise SourceError(f"{npy} has {len(rows)} poses but {folder} holds {len(paths)} images")
    frames = []
    for path, row in zip(paths, rows):
        mat = row[:15].reshape(3, 5)
        h, w, focal = mat[:, 4]
        width, height = _image_size(path)
        if abs(width / w - height / h) > 0.01 * width / w:
            raise SourceError(f"{path.name} is {width}x{height}, not the poses' {w:g}x{h:g} aspect")
        f = focal * width / w
        K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
        frames.append(
            PosedImage(path.stem, path.resolve(), K, None, opencv_c2w_from_llff(mat[:, :4]), "")
        )
    for fr, s in zip(frames, holdout_split([fr.name for fr in frames], holdout_every)):
        fr.split = s
    _dedupe_names(frames)
    bounds = {"near": float(rows[:, 15].min()), "far": float(rows[:, 16].max())}
    return PosedImages(frames, source=str(npy), extra={"llff_bounds": bounds})


def read_colmap(
    model_dir: Path, images_dir: Path | None = None, holdout_every: int = 8
) -> PosedImages:
    """A COLMAP sparse model (text or binary). Images are looked up in `images_dir`, else in
    `model_dir/../images` or `model_dir/../../images` (COLMAP's usual layouts)."""
    import pycolmap

    model_dir = Path(model_dir)
    if not model_dir.exists():
        raise SourceError(f"{model_dir} does not exist")
    if not any((model_dir / f"cameras.{e}").exists() for e in ("bin", "txt")):
        cand = [
            p
            for p in (model_dir / "sparse", model_dir / "sparse" / "0", model_dir / "0")
            if any((p / f"cameras.{e}").exists() for e in ("bin", "txt"))
        ]
        if not cand:
            raise SourceError(f"{model_dir} holds no COLMAP model (cameras.bin/.txt)")
        model_dir = cand[0]
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap raises bare RuntimeErrors
        raise SourceError(f"cannot read COLMAP model {model_dir}: {e}") from e
    roots = (
        [images_dir]
        if images_dir
        else [
            model_dir.parent / "images",
            model_dir.parent.parent / "images",
            model_dir.parent.parent.parent / "images",
        ]
    )
    root = next((r for r in roots if r and r.exists()), None)
    if root is None:
        raise SourceError(f"no images folder found for {model_dir}; pass --images")
    frames = []
    for image_id in sorted(rec.reg_image_ids()):
        im = rec.images[image_id]
        cam = rec.cameras[im.camera_id]
        K, dist = colmap_camera_to_opencv(cam)
        cam_from_world = np.eye(4)
        cam_from_world[:3, :] = im.cam_from_world().matrix()
        frames.append(
            PosedImage(
                Path(im.name).stem, root / im.name, K, dist, np.linalg.inv(cam_from_world), ""
            )
        )
    if not frames:
        raise SourceError(f"COLMAP model {model_dir} has no registered images")
    for f, s in zip(frames, holdout_split([f.name for f in frames], holdout_every)):
        f.split = s
    _dedupe_names(frames)
    pts = rec.points3D
    xyz = np.array([p.xyz for p in pts.values()]) if len(pts) else None
    rgb = np.array([p.color for p in pts.values()], dtype=np.uint8) if len(pts) else None
    return PosedImages(frames, xyz, rgb, source=str(model_dir))


def colmap_camera_to_opencv(cam) -> tuple[np.ndarray, np.ndarray | None]:
    """COLMAP camera -> (K, OpenCV distortion or None). COLMAP's principal point is already in
    the pixel-edge convention we use (centre of the first pixel at 0.5)."""
    p = np.asarray(cam.params, dtype=np.float64)
    model = cam.model_name if hasattr(cam, "model_name") else str(cam.model).split(".")[-1]
    if model == "SIMPLE_PINHOLE":
        f, cx, cy = p
        return np.array([[f, 0, cx], [0, f, cy], [0, 0, 1]]), None
    if model == "PINHOLE":
        fx, fy, cx, cy = p
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), None
    if model == "SIMPLE_RADIAL":
        f, cx, cy, k = p
        return np.array([[f, 0, cx], [0, f, cy], [0, 0, 1]]), np.array([k, 0, 0, 0])
    if model == "RADIAL":
        f, cx, cy, k1, k2 = p
        return np.array([[f, 0, cx], [0, f, cy], [0, 0, 1]]), np.array([k1, k2, 0, 0])
    if model == "OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2 = p
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), np.array([k1, k2, p1, p2])
    raise SourceError(f"COLMAP camera model {model} is not supported (use PINHOLE/RADIAL/OPENCV)")
