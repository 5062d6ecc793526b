"""Mesh benchmark: train short runs, extract meshes, score them against ground truth.

Protocol, through the real `recon` CLI as a user would run it (2 CPU threads):
- sample: `recon sfm --from-transforms sample_data`; train ngp and 3dgs for a time budget each;
  mesh ngp by marching cubes on its density and by TSDF fusion of its rendered depth, 3dgs by
  TSDF; `recon eval` against sample_data/mesh.ply.
- walnut: `recon sfm --from-transforms robovision_mvs_walnut/transforms.json --downscale 4`;
  the same per method; `recon eval --gt-points reference.ply` (the reference point cloud).
- method `mvs`: no training; `recon mvs` (plane-sweep stereo on the training photos, its mesh
  by TSDF fusion of the checked depth maps), then `recon eval --run mvs`; its row's time is
  the whole `recon mvs` wall time.

Geometry: accuracy / completeness (mean nearest-neighbour distances each way), Chamfer (their
mean), precision / recall / F-score at tau = 1 % of the ground truth's bounding-box diagonal
(recon eval's default), normal consistency when the reference is a mesh; ORIGINAL units.

    python pipelines/bench_mesh.py [--scenes sample,walnut] [--methods ngp,3dgs,mvs] [--budget 240]
    python pipelines/bench_mesh.py --scenes sample --methods sdf,3dgs --curve 60,120,300,600

Writes bench/results/mesh_<scene>.json and .md; the JSON holds every number the CLI returned.
`--curve`: one run per budget instead, F-score against training time in
bench/results/mesh_curve_<scene>.{json,md,png}.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import shutil
import sys
import time
from pathlib import Path

import click

from bench import recon  # the CLI through a subprocess, --json, 2 threads

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
WALNUT = SHARED / "robovision_mvs_walnut"
SCENES = {
    "sample": {"sfm": ["--from-transforms", str(ROOT / "sample_data")], "eval": []},
    "walnut": {
        "sfm": ["--from-transforms", str(WALNUT / "transforms.json"), "--downscale", "4"],
        "eval": [
            "--gt-points",
            str(WALNUT / "reference_reconstructions" / "2016_10_24__17_43_02" / "reference.ply"),
        ],
    },
}
MESHERS = {
    "ngp": ["marching-cubes", "tsdf"],
    "3dgs": ["tsdf"],
    "plenoxel": ["marching-cubes", "tsdf"],
    "nerf": ["marching-cubes"],
    "sdf": ["marching-cubes"],  # the zero level set of the distance
    "mvs": ["tsdf"],  # `recon mvs`: TSDF fusion of its checked depth maps (no training)
}
GEOMETRY_KEYS = (
    "accuracy",
    "completeness",
    "chamfer",
    "tau",
    "precision",
    "recall",
    "fscore",
    "normal_consistency",
    "gt_observed_fraction",
)


def keep_picture(mesh_path: str, picture: Path | None) -> dict:
    """The mesh file's size on disk, and its first shaded preview copied to `picture` (the
    workspace's is overwritten by the next mesher of the same run)."""
    mesh_path = Path(mesh_path)
    out = {"mesh_mb": round(mesh_path.stat().st_size / 1e6, 2)}
    preview = mesh_path.parent / "preview_0.png"
    if picture is not None and preview.exists():
        picture.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(preview, picture)
        out["picture"] = picture.name
    return out


def mesh_and_score(
    ws: Path,
    run: str,
    mesher: str,
    resolution: int,
    eval_args: list[str],
    picture: Path | None = None,
) -> dict:
    """`recon mesh` with one method, then `recon eval` of that mesh -> one result row."""
    mesh = recon(
        "mesh", "-w", str(ws), "--run", run, "--method", mesher, "--resolution", str(resolution)
    )
    kept = keep_picture(mesh["path"], picture)
    ev = recon("eval", "-w", str(ws), "--run", run, "--no-lpips", *eval_args)[run]
    geo = ev["geometry"]
    row = {
        "run": run,
        "mesher": mesher,
        "resolution": resolution,
        "mesh_seconds": mesh["seconds"],
        "faces": mesh["faces"],
        "components": mesh["components"],
        **kept,
        "test_psnr": ev["mean"].get("psnr"),
        "depth_abs_rel": ev["mean"].get("depth_abs_rel"),
        "geometry_status": geo["status"],
        **{k: geo[k] for k in GEOMETRY_KEYS if k in geo},
        "mesh_json": mesh,
    }
    return row


def mvs_and_score(
    ws: Path, reuse: bool, eval_args: list[str], picture: Path | None = None
) -> tuple[dict, dict]:
    """`recon mvs` (or, with reuse, its last result), then `recon eval --run mvs` of its mesh:
    the record that stands in for training, and one result row."""
    if reuse and (ws / "mvs" / "mvs.json").exists():
        mvs = {**json.loads((ws / "mvs" / "mvs.json").read_text()), "reused": True}
    else:
        print(f"bench_mesh: {ws.name} mvs ...", file=sys.stderr, flush=True)
        mvs = recon("mvs", "-w", str(ws), "--force")
    geo = recon("eval", "-w", str(ws), "--run", "mvs", *eval_args)["mvs"]["geometry"]
    row = {
        "run": "mvs",
        "mesher": "tsdf",
        "resolution": mvs["config"]["resolution"],
        "mesh_seconds": mvs["seconds"],
        "faces": mvs["faces"],
        "components": mvs.get("components"),
        **keep_picture(mvs["mesh_path"], picture),
        "test_psnr": None,  # nothing is rendered
        "geometry_status": geo["status"],
        **{k: geo[k] for k in GEOMETRY_KEYS if k in geo},
        "mesh_json": mvs,
    }
    return {"steps": "–", "wall_s": mvs["seconds"], "views": mvs["views"]}, row


def train_or_reuse(
    ws: Path, method: str, budget: float, reuse: bool, run: str | None = None
) -> dict:
    """Train a run (named `run`, default the method) for `budget` seconds, or, with reuse, read
    the finished run's record."""
    run = run or method
    run_json = ws / "runs" / run / "run.json"
    if reuse and run_json.exists() and (ws / "runs" / run / "model.pt").exists():
        doc = json.loads(run_json.read_text())
        return {"steps": doc["steps"], "stop_reason": doc["stop_reason"], "reused": True}
    print(f"bench_mesh: {ws.name} {run} train {budget:.0f} s ...", file=sys.stderr, flush=True)
    started = time.time()
    train = recon(
        "train",
        "-w",
        str(ws),
        "--method",
        method,
        "--run",
        run,
        "--time-budget",
        str(budget),
        "--threads",
        "2",
        "--eval-every",
        str(max(budget / 6, 15)),
        "--eval-views",
        "2",
        "--force",
    )
    return {
        "steps": train["steps"],
        "stop_reason": train["stop_reason"],
        "wall_s": round(time.time() - started, 1),
    }


def bench_scene(
    scene: str,
    methods: list[str],
    budget: float,
    resolution: int,
    work: Path,
    reuse: bool = False,
    pictures: Path | None = None,
) -> dict:
    """Every method's meshes of one scene, scored; each mesh's first preview copied to
    pictures/<scene>_<run>_<mesher>.png when `pictures` is given."""

    def picture(run: str, mesher: str) -> Path | None:
        return None if pictures is None else pictures / f"{scene}_{run}_{mesher}.png"

    ws = work / scene
    if not (ws / "sfm" / "cameras.json").exists():
        recon("sfm", *SCENES[scene]["sfm"], "-w", str(ws))
    cams = json.loads((ws / "sfm" / "cameras.json").read_text())
    out = {
        "scene": scene,
        "workspace": str(ws),
        "aabb_scene": cams["aabb"],
        "scene_scale": cams["scene_from_world"]["scale"],
        "rows": [],
        "training": {},
    }
    for method in methods:
        if method == "mvs":
            out["training"][method], row = mvs_and_score(
                ws, reuse, SCENES[scene]["eval"], picture("mvs", "tsdf")
            )
            out["rows"].append(row)
            continue
        out["training"][method] = train_or_reuse(ws, method, budget, reuse)
        for mesher in MESHERS[method]:
            print(f"bench_mesh: {scene} {method} {mesher} ...", file=sys.stderr, flush=True)
            try:
                out["rows"].append(
                    mesh_and_score(
                        ws,
                        method,
                        mesher,
                        resolution,
                        SCENES[scene]["eval"],
                        picture(method, mesher),
                    )
                )
            except RuntimeError as e:
                out["rows"].append(
                    {"run": method, "mesher": mesher, "error": str(e).splitlines()[-1]}
                )
    return out


def bench_curve(
    scene: str, methods: list[str], budgets: list[float], resolution: int, work: Path, reuse: bool
) -> dict:
    """F-score (and Chamfer, test PSNR) against training time: one run per method and budget,
    each with the schedules its budget lays out (what a user gets for that budget), meshed with
    the method's first mesher."""
    ws = work / scene
    if not (ws / "sfm" / "cameras.json").exists():
        recon("sfm", *SCENES[scene]["sfm"], "-w", str(ws))
    out = {"scene": scene, "workspace": str(ws), "points": []}
    for method in methods:
        for budget in budgets:
            run = f"{method}-{budget:g}s"
            train = train_or_reuse(ws, method, budget, reuse, run)
            mesher = MESHERS[method][0]
            print(f"bench_mesh: {scene} {run} {mesher} ...", file=sys.stderr, flush=True)
            row = mesh_and_score(ws, run, mesher, resolution, SCENES[scene]["eval"])
            row.pop("mesh_json")
            out["points"].append({"method": method, "budget_s": budget, **train, **row})
    return out


def curve_markdown(res: dict) -> str:
    lines = [
        f"# F-score against training time: {res['scene']} ({res['date']})",
        "",
        (
            "One run per method and budget, 2 threads, load average at start "
            f"{res['load_average']}; tau = 1 % of the ground truth's diagonal (original units). "
            f"Plot: `mesh_curve_{res['scene']}.png`."
        ),
        "",
        "| method | budget s | steps | mesher | faces | Chamfer | F-score | test PSNR |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for p in res["points"]:
        lines.append(
            f"| {p['method']} | {p['budget_s']:g} | {p['steps']} | {p['mesher']} | {p['faces']} "
            f"| {p.get('chamfer', float('nan')):.4f} | {p.get('fscore', float('nan')):.3f} "
            f"| {p.get('test_psnr') or float('nan'):.2f} |"
        )
    return "\n".join(lines) + "\n"


def plot_curve(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5), dpi=120)
    for method in dict.fromkeys(p["method"] for p in res["points"]):
        pts = [p for p in res["points"] if p["method"] == method]
        ax.plot([p["budget_s"] for p in pts], [p.get("fscore") for p in pts], "o-", label=method)
    ax.set_xscale("log")
    ax.set_xlabel("training time budget (s, 2 CPU threads)")
    ax.set_ylabel("F-score at tau = 1 % of the diagonal")
    ax.set_title(f"{res['scene']}: mesh F-score against training time")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def keep_other_methods(res: dict, previous: Path) -> None:
    """Keep the rows of methods this invocation did not run from the previous results file
    (e.g. `--methods ngp --reuse-runs` re-meshes ngp only), naming the date they come from."""
    if not previous.exists():
        return
    old = json.loads(previous.read_text())
    kept = [r for r in old.get("rows", []) if r["run"] not in res["training"]]
    for r in kept:
        r.setdefault("from_results_of", old.get("date"))
        res["training"].setdefault(r["run"], old["training"][r["run"]])
    res["rows"] += kept


def markdown(res: dict) -> str:
    busy = res["load_average"][0] > 1.5  # more than a 2-core machine's benchmark alone
    load_note = "a busy machine: wall times are inflated" if busy else "a quiet machine"
    lines = [
        f"# mesh benchmark: {res['scene']} ({res['date']})",
        "",
        (
            f"Training budget {res['budget_s']:.0f} s per method, 2 threads, load average at start "
            f"{res['load_average']} ({load_note}). Geometry in original "
            "units; tau = 1 % of the ground truth's bounding-box diagonal; completeness and recall "
            "count the ground truth some view saw (by its depth maps) when the dataset has them."
        ),
        "",
        (
            "| run | mesher | steps | faces | MB | Chamfer | accuracy | completeness | precision "
            "| recall | F-score | normal cons. | GT observed | test PSNR | picture |"
        ),
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def fmt(v, f=".4f"):
        return "–" if v is None else format(v, f)

    for r in res["rows"]:
        if "error" in r:
            lines.append(f"| {r['run']} | {r['mesher']} | failed: {r['error'][:80]} |")
            continue
        lines.append(
            " | ".join(
                [
                    f"| {r['run']}"
                    + (f" ({r['from_results_of'][:16]})" if "from_results_of" in r else ""),
                    r["mesher"],
                    str(res["training"][r["run"]]["steps"]),
                    str(r["faces"]),
                    fmt(r.get("mesh_mb"), ".1f"),
                    fmt(r.get("chamfer")),
                    fmt(r.get("accuracy")),
                    fmt(r.get("completeness")),
                    fmt(r.get("precision"), ".3f"),
                    fmt(r.get("recall"), ".3f"),
                    fmt(r.get("fscore"), ".3f"),
                    fmt(r.get("normal_consistency"), ".3f"),
                    fmt(r.get("gt_observed_fraction"), ".3f"),
                    fmt(r.get("test_psnr"), ".2f"),
                    (f"[png](mesh_previews/{r['picture']})" if r.get("picture") else "–") + " |",
                ]
            )
        )
    taus = {r.get("tau") for r in res["rows"] if r.get("tau")}
    if taus:
        lines += ["", f"tau = {', '.join(f'{t:.4f}' for t in sorted(taus))} (original units)"]
    return "\n".join(lines) + "\n"


@click.command()
@click.option("--scenes", default="sample,walnut", show_default=True)
@click.option("--methods", default="ngp,3dgs", show_default=True)
@click.option("--budget", default=240.0, show_default=True, help="Training seconds per method.")
@click.option(
    "--resolution",
    default=256,
    show_default=True,
    help="Mesh samples along the box's longest side.",
)
@click.option(
    "--work", default=str(ROOT / "bench" / "work"), show_default=True, help="Workspaces folder."
)
@click.option("--out-dir", default=str(ROOT / "bench" / "results"), show_default=True)
@click.option(
    "--reuse-runs", is_flag=True, help="Mesh and score finished runs again instead of retraining."
)
@click.option(
    "--curve",
    default="",
    help="Budgets in seconds, e.g. 60,120,300,600: F-score against training time instead "
    "(bench/results/mesh_curve_<scene>.{json,md,png}).",
)
def main(
    scenes: str,
    methods: str,
    budget: float,
    resolution: int,
    work: str,
    out_dir: str,
    reuse_runs: bool,
    curve: str,
) -> None:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for scene in scenes.split(","):
        if curve:
            load = [round(x, 2) for x in os.getloadavg()]
            budgets = [float(b) for b in curve.split(",")]
            res = bench_curve(
                scene, methods.split(","), budgets, resolution, Path(work) / "mesh", reuse_runs
            )
            res.update({"date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds")})
            res.update({"load_average": load, "resolution": resolution})
            (out / f"mesh_curve_{scene}.json").write_text(json.dumps(res, indent=1) + "\n")
            (out / f"mesh_curve_{scene}.md").write_text(curve_markdown(res))
            plot_curve(res, out / f"mesh_curve_{scene}.png")
            continue
        load = os.getloadavg()
        res = bench_scene(
            scene,
            methods.split(","),
            budget,
            resolution,
            Path(work) / "mesh",
            reuse_runs,
            out / "mesh_previews",
        )
        res.update(
            {
                "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
                "budget_s": budget,
                "load_average": [round(x, 2) for x in load],
                "resolution": resolution,
            }
        )
        keep_other_methods(res, out / f"mesh_{scene}.json")
        (out / f"mesh_{scene}.json").write_text(json.dumps(res, indent=1) + "\n")
        (out / f"mesh_{scene}.md").write_text(markdown(res))
        print(markdown(res))


if __name__ == "__main__":
    main()
