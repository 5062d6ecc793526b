"""What the Snakemake sweep (`pipelines/Snakefile`) needs besides the `recon` CLI: the scenes of a
config, the files each scene's `recon sfm` reads (so touching a photo reruns exactly that scene's
jobs), and the resources a scheduler packs jobs by (memory, wall time, threads).

No stage logic lives here: every job is one `recon` command, as in `pipelines/Makefile`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

# ---- scenes --------------------------------------------------------------------------------
SOURCES = ("photos", "transforms", "colmap")  # how a scene enters `recon sfm`
SOURCE_FLAGS = {"photos": [], "transforms": ["--from-transforms"], "colmap": ["--from-colmap"]}


@dataclass(frozen=True)
class SceneSpec:
    name: str
    kind: str  # photos | transforms | colmap
    path: Path  # photo folder or video, transforms*.json or its folder, COLMAP model folder
    sfm_args: tuple[str, ...] = ()
    eval_args: tuple[str, ...] = ()
    methods: tuple[str, ...] = ()
    budgets: tuple[int, ...] = ()


def scenes_from_config(config: dict, base: Path) -> list[SceneSpec]:
    """The config's `scenes` mapping (name -> {photos|transforms|colmap: path, sfm_args,
    eval_args, methods, budgets}), paths relative to `base`; per-scene methods and budgets
    default to the config's top-level lists."""
    from recon.models.registry import METHOD_NAMES

    out = []
    for name, doc in config["scenes"].items():
        kinds = [k for k in SOURCES if k in doc]
        if len(kinds) != 1:
            raise ValueError(f"scene '{name}': give exactly one of {', '.join(SOURCES)}")
        methods = tuple(doc.get("methods", config["methods"]))
        unknown = sorted(set(methods) - set(METHOD_NAMES))
        if unknown:
            raise ValueError(
                f"scene '{name}': unknown method(s) {', '.join(unknown)}; "
                f"choose from {', '.join(METHOD_NAMES)}"
            )
        out.append(
            SceneSpec(
                name=name,
                kind=kinds[0],
                path=(base / doc[kinds[0]]).resolve(),
                sfm_args=tuple(str(a) for a in doc.get("sfm_args", [])),
                eval_args=tuple(str(a) for a in doc.get("eval_args", [])),
                methods=methods,
                budgets=tuple(int(b) for b in doc.get("budgets", config["budgets"])),
            )
        )
    return out


def sfm_command_args(scene: SceneSpec) -> list[str]:
    """`recon sfm` arguments that name the scene's source (the workspace comes separately)."""
    return [*SOURCE_FLAGS[scene.kind], str(scene.path), *scene.sfm_args]


def source_files(scene: SceneSpec) -> list[str]:
    """Every file `recon sfm` reads for this scene: a folder's files (recursively, hidden ones
    left out), or the one file given. Snakemake compares their times with the sfm job's output,
    so changing or touching any photo reruns the scene's sfm and everything downstream of it."""
    p = scene.path
    if not p.exists():
        raise FileNotFoundError(f"scene '{scene.name}': {p} does not exist")
    if p.is_file():
        files = [p]
        if scene.kind == "transforms":  # the images it names sit beside it
            files += _files_under(p.parent)
        return sorted({str(f) for f in files})
    files = _files_under(p)
    if scene.kind == "colmap":  # the images default to the folder next to the model
        images = p.parent / "images"
        if "--images" in scene.sfm_args:
            images = Path(scene.sfm_args[scene.sfm_args.index("--images") + 1])
        files += _files_under(images) if images.is_dir() else []
    return sorted({str(f) for f in files})


def _files_under(folder: Path) -> list[Path]:
    return [
        f
        for f in folder.rglob("*")
        if f.is_file() and not any(part.startswith(".") for part in f.relative_to(folder).parts)
    ]


def run_name(method: str, budget: int) -> str:
    return f"{method}-{budget}s"


# ---- resources -----------------------------------------------------------------------------
# Peak resident memory of `recon train` as base + bytes per training pixel (the training views at
# the working resolution), fitted to measured runs on 2 CPU threads (bench/results/): 3dgs on fox
# 675 MB at 1.5 M training pixels and 1,000 MB at 13.2 M; ngp 1,289 MB at 1.2 M and 2,190 MB at
# 13.2 M; lego-200 (4 M pixels) plenoxel 4.0 GB (its dense grid), nerf 2.1 GB. The scheduler is
# asked for HEADROOM x that; a method without a measurement gets the largest figure.
TRAIN_MEMORY_MB = {  # method: (base MB, bytes per training pixel)
    "3dgs": (640.0, 28.0),
    "ngp": (1200.0, 75.0),
    "nerf": (1800.0, 75.0),
    "plenoxel": (3800.0, 75.0),
}
HEADROOM = 1.5
STAGE_MEMORY_MB = 3000  # render / mesh / eval (LPIPS, marching cubes, TSDF) on these scenes


def training_pixels(
    workspace: str | Path, method: str, budget_s: float, threads: int
) -> int | None:
    """Training pixels (views x width x height) at the working resolution `recon train` will
    choose for this workspace, method and budget (`recon.train.resolution`, the rule itself, at
    the prior speed of `threads`: what a probe within tolerance of it keeps); None before the
    workspace's sfm exists."""
    from recon.models.registry import method_spec
    from recon.train.resolution import choose_resolution
    from recon.train.throughput import prior_speed
    from recon.workspace import Workspace
    from recon.workspace.scene import load_scene

    workspace = Path(workspace)
    if not (workspace / "sfm" / "cameras.json").exists():
        return None
    scene = load_scene(Workspace.open(workspace), with_points=False)
    width, height = scene.image_size("train")
    n_views = len(scene.split("train"))
    res = choose_resolution(
        width, height, n_views, method_spec(method).resolution, budget_s, 0, prior_speed(threads)
    )
    return n_views * res.width * res.height


def train_mem_mb(method: str, pixels: int | None, photos: int) -> int:
    """Memory to request for a training job. Before sfm has run (a dry run), `pixels` is None
    and the bound is every photo at the 1,600 px cap (1600 x 1200), the most any method trains
    on by default."""
    base, per_px = TRAIN_MEMORY_MB.get(method, max(TRAIN_MEMORY_MB.values()))
    if pixels is None:
        pixels = photos * 1600 * 1200
    return math.ceil(HEADROOM * (base + per_px * pixels / 1e6) / 100) * 100


def sfm_mem_mb(photos: int) -> int:
    """pycolmap's SIFT and matching on photos at the 1,600 px cap: ~2 GB plus what the features
    and matches of each photo take."""
    return math.ceil(HEADROOM * (2000 + 20 * photos) / 100) * 100


def train_runtime_min(budget_s: float) -> int:
    """Wall time (minutes) to ask for: the budget bounds `recon train` (periodic evaluations
    included), plus start-up, the final evaluation and saving."""
    return math.ceil(budget_s * 1.1 / 60) + 10


def sfm_runtime_min(photos: int) -> int:
    """fox's 67 photos took about 3 minutes on 2 cores with exhaustive matching, which grows
    with the square of the photo count."""
    return 10 + math.ceil(3 * (photos / 67) ** 2)


@functools.cache  # asked by every job's resources; the folder is walked once per Snakemake run
def photo_count(scene: SceneSpec) -> int:
    from recon.sfm.sources import IMAGE_SUFFIXES

    return max(1, sum(Path(f).suffix.lower() in IMAGE_SUFFIXES for f in source_files(scene)))
