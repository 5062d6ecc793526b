"""The `train` stage: set up a run directory, build the model, run the loop, record it."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import random
import resource
import shutil
import signal
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import torch

from recon.cameras import Cameras
from recon.io.ply import read_points_ply
from recon.models.base import MethodSpec, Model, TrainData
from recon.models.registry import choose_device, config_from_json, import_methods, save_model
from recon.train.checkpoint import has_checkpoint, load_latest_checkpoint, save_checkpoint
from recon.train.config import TrainConfig, build_config, resolve_preset
from recon.train.loop import LoopState, run_loop
from recon.train.resolution import (
    eval_downscale,
    measure_speed,
    plan_schedules,
    scene_photo_detail,
    trained_resolution,
    working_resolution,
)
from recon.train.trainer import Trainer, training_background
from recon.workspace import Workspace, WorkspaceError, atomic_path, atomic_write_json
from recon.workspace.registration import partial_warning
from recon.workspace.scene import Scene, level_size, load_images, load_scene, load_train_data
from recon.workspace.workspace import MVS_RESULT, RUN_SCHEMA_VERSION, software_versions

MAX_ROLLBACKS = 3  # non-finite losses survived by reloading the last checkpoint
ROLLBACK_LR_FACTOR = 0.5  # every rollback halves all learning rates for the rest of the process
# (`Trainer.lr_scale`: a power of two, so the schedules' rates are scaled exactly)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def heldout_views(scene: Scene, n: int) -> list[int]:
    test = scene.split("test") or scene.split("val")
    if not test or n <= 0:
        return []
    pick = np.linspace(0, len(test) - 1, min(n, len(test))).round().astype(int)
    return [test[i] for i in sorted(set(pick.tolist()))]


def check_run(ws: Workspace, run: str, resume: bool, force: bool) -> bool:
    """Refuse what cannot be done; True when an existing run is to be replaced (--force)."""
    if run == MVS_RESULT:
        raise WorkspaceError(
            f"'{run}' names the output of `recon mvs` in reports: choose another --run name"
        )
    exists = ws.run_dir(run).exists()
    if exists and not resume and not force:
        raise WorkspaceError(
            f"run '{run}' already exists: pass --resume to continue it, "
            "--force to overwrite it, or --run NAME for a new run"
        )
    if resume and not ws.run_json(run).exists():
        raise WorkspaceError(f"cannot resume: run '{run}' does not exist")
    return exists and not resume


def set_threads(n: int) -> None:
    """Use `n` CPU threads in torch and in the numba kernels (capped by NUMBA_NUM_THREADS, which
    numba fixes at import). Results are reproducible for a fixed thread count."""
    import numba

    torch.set_num_threads(n)
    numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))


def train(
    ws: Workspace,
    run: str,
    cfg: TrainConfig,
    overrides: list[str],
    resume: bool,
    force: bool,
    log_fn=print,
    progress=None,
) -> dict:
    """Train (or resume) run `run`; returns the run summary written to run.json."""
    ws.require_fresh("sfm", force)
    methods = import_methods()
    if cfg.method not in methods:
        raise WorkspaceError(
            f"unknown method {cfg.method!r} (available: {', '.join(sorted(methods))})"
        )
    spec = methods[cfg.method]
    surface_points_source(ws, cfg, spec)  # refuses `--surface-points on` without mvs, up front
    # set also at the default count: numba's parallel kernels ran ~1.6x slower until
    # numba.set_num_threads was called (3dgs steps on 2 cores: 21 against 13 ms), which the
    # throughput probe would then measure as a slower machine
    set_threads(cfg.threads or torch.get_num_threads())
    device, device_reason = choose_device(
        cfg.device, spec.cuda_missing() if spec.cuda_missing else None
    )
    log_fn(f"device {device.type} ({device_reason})")
    device_doc = {"device": str(device), "device_reason": device_reason}
    with ws.writer_lock(f"run-{run}"):
        replace = check_run(ws, run, resume, force)
        with ws.replacing_run(run) if replace else contextlib.nullcontext():
            return _train_checked(
                ws, run, cfg, spec, overrides, device_doc, resume, log_fn, progress
            )


def _train_checked(ws, run, cfg, spec, overrides, device_doc, resume, log_fn, progress) -> dict:
    if resume:
        saved = json.loads(ws.run_json(run).read_text())
        method_cfg = spec.config_cls(**config_from_json(spec.config_cls, saved["config"]))
        train_fields = {f for f in TrainConfig.__dataclass_fields__}
        cfg = TrainConfig(
            **{
                **{k: v for k, v in saved["train"].items() if k in train_fields},
                **{
                    k: v
                    for k, v in asdict(cfg).items()
                    if k in ("steps", "time_budget_s", "patience")
                },
            }
        )
    else:
        preset, why = resolve_preset(
            cfg.preset, spec.presets, torch.device(device_doc["device"]).type
        )
        log_fn(f"preset {preset} ({why})")
        cfg = dataclasses.replace(cfg, preset=preset)
        method_cfg = build_config(spec.config_cls, spec.presets, cfg.preset, overrides)
    try:
        return _train_run(ws, run, cfg, spec, method_cfg, device_doc, resume, log_fn, progress)
    except Exception:
        if not resume:
            discard_unresumable_run(ws, run)
        raise


def training_images_line(ws: Workspace, train: int, test: int) -> str:
    """How many images the run trains on, and the sfm stage's warning when it registered
    fewer than its --min-registered share of the photos (`recon.sfm.registration`)."""
    line = f"training on {train} images ({test} held out)"
    registration = {}
    if ws.sfm_report.exists():
        registration = json.loads(ws.sfm_report.read_text()).get("registration", {})
    if registration.get("partial"):
        line += f"; warning: sfm {partial_warning(registration)}"
    return line


def surface_points_source(ws: Workspace, cfg: TrainConfig, spec) -> Path | None:
    """WS/mvs/points.ply when the option asks for it and the method fits surface points; None
    otherwise. Asked for without a done and fresh mvs stage (a stale one was made from other
    cameras), it is an error, not a silent fallback."""
    if cfg.surface_points == "off" or not spec.uses_surface_points:
        return None
    path = ws.mvs_dir / ws.MVS_POINTS
    state = ws.status().get("mvs", {}).get("state", "missing")
    if state != "done" or not path.exists():
        raise WorkspaceError(
            f"--surface-points on needs `recon mvs -w {ws.root}` first (the mvs stage is {state})"
        )
    return path


def load_surface_points(path: Path, scene: Scene, device) -> torch.Tensor:
    """(N, 3) float32 points of a PLY in original units, moved into the scene frame."""
    points, _ = read_points_ply(path)
    return (
        torch.from_numpy(scene.scene_from_world.apply(points.astype(np.float64))).float().to(device)
    )


def discard_unresumable_run(ws: Workspace, run: str) -> None:
    """A new run that failed before any checkpoint landed (disk full, unreadable scene) holds
    nothing to resume: remove it so a failed command leaves the workspace as it was."""
    if not has_checkpoint(ws.checkpoints_dir(run)):
        shutil.rmtree(ws.run_dir(run), ignore_errors=True)


def _train_run(ws, run, cfg, spec, method_cfg, device_doc, resume, log_fn, progress) -> dict:
    """Set up (or resume) the run, train it, finish and record it: run.json says "done", or
    "interrupted" / "failed" with the step and the reason, and its log is closed either way."""
    r = _setup_run(ws, run, cfg, spec, method_cfg, device_doc, resume, log_fn)
    reason = _run_loop_with_rollbacks(r, progress)
    return _finish_run(r, reason)


@dataclasses.dataclass
class _Run:
    """One run's training, as `_setup_run` made it: the model and its data, the run document
    and the loop's state, and the run's log (open from setup until the run ends)."""

    ws: Workspace
    run: str
    cfg: TrainConfig
    spec: MethodSpec
    method_cfg: Any  # the method's config dataclass
    device: torch.device
    model: Model
    trainer: Trainer
    data: TrainData
    held_cams: Cameras | None
    held_imgs: torch.Tensor | None
    run_doc: dict
    st: LoopState
    points_from: Path | None
    started: float  # time.time() when setup began
    log_fn: Callable[[str], None]
    log_file: TextIO  # log.jsonl, appended to

    def log(self, entry: dict) -> None:
        self.log_file.write(json.dumps(entry) + "\n")
        self.log_file.flush()

    def checkpoint(self, state: LoopState) -> None:
        save_checkpoint(
            self.ws.checkpoints_dir(self.run),
            state.step,
            {
                "model": self.model.state_dict(),
                "training": self.trainer.state_dict(),
                "loop": {k: v for k, v in state.__dict__.items()},
                "rng": torch.get_rng_state(),
            },
            self.cfg.keep_checkpoints,
        )

    def rollback(self, cause: str, rollbacks: int) -> LoopState:
        """Reload the last good checkpoint after a non-finite loss (the `rollbacks`-th before
        this one); the RNG moves on, so the retried steps see other rays / views."""
        ck = load_latest_checkpoint(self.ws.checkpoints_dir(self.run), self.log_fn)
        if ck is None:
            raise FloatingPointError(
                "the loss became non-finite before the first checkpoint; "
                "lower the learning rates (see --list-options)"
            )
        self.model.load_state_dict(ck["model"])
        self.trainer.load_state_dict(ck["training"])
        # time spent stays spent
        state = LoopState(**{**ck["loop"], "elapsed_s": self.st.elapsed_s})
        torch.manual_seed(self.cfg.seed + 7919 * (rollbacks + 1))
        self.model.reseed(self.cfg.seed + 7919 * (rollbacks + 1))
        self.trainer.lr_scale *= ROLLBACK_LR_FACTOR
        self.log(
            {
                "step": state.step,
                "wall_s": state.wall_s,
                "event": "rollback",
                "count": rollbacks + 1,
                "cause": cause,
                "lr_scale": self.trainer.lr_scale,
            }
        )
        self.log_fn(
            f"{cause}: rolled back to step {state.step}, learning rates x{self.trainer.lr_scale:g} "
            f"(rollback {rollbacks + 1} of {MAX_ROLLBACKS})"
        )
        return state

    def end(self, status: str, **fields) -> None:
        """A run that stops without finishing: its log closed, run.json saying why."""
        self.log_file.close()
        atomic_write_json(
            self.ws.run_json(self.run),
            {**self.run_doc, "status": status, "step": self.st.step, **fields},
        )


def _plan_run(ws, run, scene, cfg, spec, method_cfg, device, resume, log_fn):
    """The working resolution, the method config with its schedules planned, and what the
    throughput probe measured (None on a resume: the level the run started at, whatever
    budget the resume gives)."""
    if resume:
        return trained_resolution(json.loads(ws.run_json(run).read_text()), scene), method_cfg, None
    t_probe = time.perf_counter()
    speed, probe = measure_speed(ws, scene, spec, method_cfg, cfg, device)
    throughput = {**speed.to_json(), **probe, "probe_s": round(time.perf_counter() - t_probe, 3)}
    if probe["probe"] is not None:
        log_fn(f"throughput probe ({throughput['probe_s']:.1f} s): {speed.reason}")
        seed_everything(cfg.seed)  # the run draws what it would have drawn without the probe
    res = working_resolution(scene, spec, cfg, speed, scene_photo_detail(ws, scene))
    return res, plan_schedules(method_cfg, spec, cfg, res, speed), throughput


def _setup_run(ws, run, cfg, spec, method_cfg, device_doc, resume, log_fn) -> _Run:
    """A new run: the device's speed, the working resolution, the schedules' plan, the data,
    the model; or a resumed one from its last checkpoint. Writes run.json ("running"), opens
    the log and saves a first checkpoint (a known-good state to roll back to)."""
    started = time.time()
    device = torch.device(device_doc["device"])
    seed_everything(cfg.seed)
    scene = load_scene(ws)
    res, method_cfg, throughput = _plan_run(
        ws, run, scene, cfg, spec, method_cfg, device, resume, log_fn
    )
    sfm_w, sfm_h = scene.image_size("train")
    log_fn(
        f"working resolution {res.width}x{res.height} (sfm images {sfm_w}x{sfm_h} / {res.downscale}): "
        f"{res.reason}"
    )
    if spec.plans_schedules and method_cfg.schedule_steps:
        log_fn(f"schedules laid out for a run of ~{method_cfg.schedule_steps} steps")
    data = load_train_data(ws, scene, "train", device, res.downscale)
    log_fn(training_images_line(ws, len(data), len(scene.split("test"))))
    points_from = surface_points_source(ws, cfg, spec)
    if points_from is not None:
        data.surface_points = load_surface_points(points_from, scene, device)
        log_fn(f"fitting {len(data.surface_points)} surface points of recon mvs ({points_from})")
    held = heldout_views(scene, cfg.eval_views)
    model = spec.build(method_cfg, scene.info).to(device)
    trainer = Trainer(model)
    trainer.background = training_background(model, data)
    if trainer.background.random:
        log_fn("training rays composite on a random colour each (the photos have alpha)")
    if note := model.plan_note(data):
        log_fn(note)
    k_eval = eval_downscale(scene, res.downscale, cfg.eval_max_side)
    k_render = res.downscale if model.aliases_when_minified else k_eval
    held_cams = scene.cameras(held, device, k_render) if held else None
    held_imgs = load_images(ws, scene, held, k_eval).to(device) if held else None
    resolution = {
        "working": res.to_json(),
        "sfm_size": [sfm_w, sfm_h],
        "periodic_eval": {
            "downscale": k_eval,
            "size": list(level_size(sfm_w, sfm_h, k_eval)),
            "rendered_at_downscale": k_render,
        },
    }
    run_doc = {
        "schema_version": RUN_SCHEMA_VERSION,
        "run": run,
        "method": spec.name,
        "preset": cfg.preset,
        "seed": cfg.seed,
        "config": asdict(method_cfg),
        "train": asdict(cfg),
        "resolution": resolution,
        **device_doc,
        **({"throughput": throughput} if throughput is not None else {}),
        "versions": software_versions(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "status": "running",
    }
    st = LoopState()
    log_path = ws.log_jsonl(run)
    ckpt_dir = ws.checkpoints_dir(run)
    if resume:
        ck = load_latest_checkpoint(ckpt_dir, log_fn)
        if ck is None:
            raise WorkspaceError(f"run '{run}' has no readable checkpoint to resume from")
        model.load_state_dict(ck["model"])
        trainer.load_state_dict(ck["training"])
        st = LoopState(**ck["loop"])
        torch.set_rng_state(ck["rng"])
        _truncate_log(log_path, st.step)
        run_doc = {**json.loads(ws.run_json(run).read_text()), **device_doc, "status": "running"}
        log_fn(f"resumed run '{run}' from step {st.step} ({st.wall_s:.0f} s of training)")
    atomic_write_json(ws.run_json(run), run_doc)
    r = _Run(
        ws, run, cfg, spec, method_cfg, device, model, trainer, data, held_cams, held_imgs, run_doc, st,
        points_from, started, log_fn, open(log_path, "a"),  # noqa: SIM115 (closed by the run's end)
    )  # fmt: skip
    r.checkpoint(st)  # a known-good state to roll back to
    st.elapsed_s += time.time() - started  # setup (loading, pyramid level, first checkpoint) counts
    return r


def _run_loop_with_rollbacks(r: _Run, progress) -> str:
    """`run_loop` until a stopping rule ends it, rolling back to the last checkpoint after a
    non-finite loss (MAX_ROLLBACKS times). Ctrl-C / SIGTERM stop it between steps with a
    checkpoint ("interrupted"); any other end is "failed". Returns the stopping reason."""
    stop = {"requested": False}

    def request_stop(signum, frame):
        stop["requested"] = True

    previous = {s: signal.signal(s, request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    rollbacks = 0
    try:
        while True:
            try:
                return run_loop(
                    r.trainer,
                    r.data,
                    r.held_cams,
                    r.held_imgs,
                    r.cfg,
                    r.st,
                    r.log,
                    r.checkpoint,
                    progress,
                    interrupted=lambda: stop["requested"],
                )
            except FloatingPointError as e:
                if rollbacks >= MAX_ROLLBACKS:
                    raise
                r.st = r.rollback(str(e), rollbacks)
                rollbacks += 1
    except KeyboardInterrupt:
        r.checkpoint(r.st)
        r.log({"step": r.st.step, "wall_s": r.st.wall_s, "event": "interrupted"})
        r.end("interrupted")
        raise KeyboardInterrupt(
            f"interrupted at step {r.st.step}; checkpoint saved. Resume with: "
            f"recon train -w {r.ws.root} --run {r.run} --resume"
        )
    except Exception as e:  # the last allowed rollback, or anything else: say so and close
        error = f"{type(e).__name__}: {e}"
        r.log({"step": r.st.step, "wall_s": r.st.wall_s, "event": "failed", "error": error})
        r.end("failed", error=error)
        raise
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _finish_run(r: _Run, reason: str) -> dict:
    """The last checkpoint, `Model.finish`, the model file, run.json "done" and the stage's
    record in the workspace. Returns run.json's summary."""
    ws, run, st, model, method_cfg, device = r.ws, r.run, r.st, r.model, r.method_cfg, r.device
    r.checkpoint(st)
    r.log({"step": st.step, "wall_s": round(st.wall_s, 4), "event": "stop", "reason": reason})
    if st.schedule_steps:
        r.log_fn(
            f"schedules re-planned for ~{st.schedule_steps} steps from the measured step rate "
            f"(planned ~{method_cfg.schedule_steps}); {st.step} made"
        )
    t_finish = time.perf_counter()
    finished = model.finish(r.data)
    if finished:  # a last clean-up of the model (`Model.finish`), outside the time budget
        finished["finish_s"] = round(time.perf_counter() - t_finish, 2)
        r.log({"step": st.step, "wall_s": round(st.wall_s, 4), "event": "finish", **finished})
    r.log_file.close()
    save_model(ws.model_path(run), r.spec.name, asdict(method_cfg), model)
    summary = {
        **r.run_doc,
        "status": "done",
        "stop_reason": reason,
        "steps": st.step,
        "train_wall_s": round(st.wall_s, 3),
        "elapsed_s": round(st.elapsed_s, 3),
        **(
            {
                "schedule_steps": {
                    "planned": method_cfg.schedule_steps,
                    "replanned": st.schedule_steps,
                }
            }
            if r.spec.plans_schedules and method_cfg.schedule_steps
            else {}
        ),
        "best_test_psnr": None if st.best_psnr == -float("inf") else round(st.best_psnr, 4),
        "model_stats": {k: float(v) for k, v in model.stats().items()},
        "model_bytes": os.path.getsize(ws.model_path(run)),
        "device": str(device),
        "threads": torch.get_num_threads(),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        **(
            {"peak_gpu_mb": round(torch.cuda.max_memory_allocated(device) / 2**20, 1)}
            if device.type == "cuda"
            else {}
        ),
    }
    atomic_write_json(ws.run_json(run), summary)
    ws.record_stage(
        f"train/{run}",
        config={"train": asdict(r.cfg), "method": asdict(method_cfg)},
        inputs={"cameras": ws.cameras_json, **({"mvs": r.points_from} if r.points_from else {})},
        outputs={"model": ws.model_path(run)},
        upstream=["sfm"] + (["mvs"] if r.points_from else []),
        started=r.started,
        ended=time.time(),
        extra={"stop_reason": reason, "steps": st.step},
    )
    return summary


def _truncate_log(path: Path, step: int) -> None:
    """Drop log lines written after the checkpoint we resume from."""
    if not path.exists():
        return
    keep = [
        ln
        for ln in path.read_text().splitlines()
        if ln.strip() and json.loads(ln).get("step", 0) <= step
    ]
    with atomic_path(path) as tmp:
        tmp.write_text("".join(ln + "\n" for ln in keep))
