"""Shared fixtures: paths to the real data beside the repo, and small synthetic datasets."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import weakref
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
SAMPLE_DATA = REPO / "sample_data"


_TRAINERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def train_step(model, data, step: int) -> dict:
    """One training step of `model` as `recon train` takes it: through its `Trainer`, one per
    model for the model's life (the optimizers' state carries from step to step)."""
    from recon.train.trainer import Trainer

    trainer = _TRAINERS.get(model)
    if trainer is None:
        trainer = _TRAINERS[model] = Trainer(model)
    return trainer.step(data, step)


def trainer_of(model):
    """The `Trainer` `train_step` uses for `model` (made on first use)."""
    from recon.train.trainer import Trainer

    if model not in _TRAINERS:
        _TRAINERS[model] = Trainer(model)
    return _TRAINERS[model]


def recon_cli(
    *args: str, check: bool = True, timeout: float = 600, env=None, subprocess_: bool = False
) -> subprocess.CompletedProcess:
    """Run the real `recon` command line. By default its click entry point runs in this process
    (the same parsing, stages and exit codes; a fresh interpreter costs ~3 s of imports and numba
    cache loads per call, most of the suite's time); with `env` or `subprocess_=True` it runs
    `python -m recon.cli` in a subprocess, as a user or CI would (environment variables that
    torch and numba read at start-up, signals, `timeout`, which an in-process call ignores).
    RECON_TEST_SUBPROCESS=1 in the environment sends every call to a subprocess."""
    if env is None and not subprocess_ and not os.environ.get("RECON_TEST_SUBPROCESS"):
        proc = _recon_in_process(args)
    else:
        full_env = {**os.environ, "OMP_NUM_THREADS": "1", **(env or {})}
        proc = subprocess.run(
            [sys.executable, "-m", "recon.cli", *args],
            check=False,
            capture_output=True,
            text=True,
            timeout=timeout,
            env=full_env,
            cwd=REPO,
        )
    if check and proc.returncode != 0:
        raise AssertionError(
            f"recon {' '.join(args)} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
        )
    return proc


def _recon_in_process(args: tuple[str, ...]) -> subprocess.CompletedProcess:
    """`recon ARGS` through click's test runner, from the repository as the subprocess would be,
    restoring the thread counts a `--threads` option sets. An exception that escapes the CLI is
    appended to stderr as the interpreter would print it."""
    import traceback

    import numba
    import torch
    from click.testing import CliRunner

    from recon.cli.main import cli

    cwd, threads, numba_threads = os.getcwd(), torch.get_num_threads(), numba.get_num_threads()
    os.chdir(REPO)
    try:
        result = CliRunner().invoke(cli, list(args), prog_name="recon")
    finally:
        os.chdir(cwd)
        torch.set_num_threads(threads)
        numba.set_num_threads(numba_threads)
    stderr = result.stderr
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        stderr += "".join(traceback.format_exception(result.exception))
    return subprocess.CompletedProcess(["recon", *args], result.exit_code, result.stdout, stderr)


def make_blender_dataset(root: Path, n_train: int = 4, n_test: int = 2, size: int = 16) -> Path:
    """A tiny Blender-style dataset: RGBA PNGs + transforms_{train,test}.json (OpenGL c2w)."""
    import cv2

    rng = np.random.default_rng(0)
    for split, n in (("train", n_train), ("test", n_test)):
        (root / split).mkdir(parents=True, exist_ok=True)
        frames = []
        for i in range(n):
            img = (rng.random((size, size, 4)) * 255).astype(np.uint8)
            cv2.imwrite(str(root / split / f"r_{i}.png"), img)
            ang = 2 * np.pi * i / n + (0.3 if split == "test" else 0)
            eye = np.array([4 * np.cos(ang), 4 * np.sin(ang), 2.0])
            fwd = -eye / np.linalg.norm(eye)  # looking at the origin
            right = np.cross(fwd, [0, 0, 1.0])
            right /= np.linalg.norm(right)
            up = np.cross(right, fwd)
            c2w = np.eye(4)
            c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, -fwd, eye  # OpenGL axes
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
        (root / f"transforms_{split}.json").write_text(
            json.dumps({"camera_angle_x": 0.69, "frames": frames})
        )
    return root


@pytest.fixture
def one_thread():
    """Tests run two per core under xdist; one thread each avoids OpenMP oversubscription."""
    import numba
    import torch

    threads, nb = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
    numba.set_num_threads(nb)


@pytest.fixture
def blender_dataset(tmp_path) -> Path:
    return make_blender_dataset(tmp_path / "blender")


def sphere_scene(n_cams: int = 8, size: int = 24, radius: float = 0.5):
    """Analytic scene for method tests: a sphere coloured by its normal (0.5 + 0.5 n) on white,
    seen by a ring of cameras. Returns (TrainData, SceneInfo)."""
    import torch

    from recon.cameras import Cameras, camera_rays
    from recon.cameras.cameras import invert_rigid
    from recon.cameras.look_at import look_at
    from recon.models.base import SceneInfo, TrainData

    angles = torch.linspace(0, 2 * np.pi, n_cams + 1)[:-1]
    eye = torch.stack(
        [1.6 * torch.cos(angles), 1.6 * torch.sin(angles), 0.6 * torch.ones(n_cams)], -1
    )
    cam_from_world = look_at(eye, torch.zeros(3), torch.tensor([0.0, 0, 1]))
    f = size * 1.2
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]]).expand(n_cams, 3, 3).clone()
    cams = Cameras(K, cam_from_world, torch.full((n_cams,), size), torch.full((n_cams,), size))
    images = []
    for i in range(n_cams):
        o, d, _ = camera_rays(cams, i)
        b = (o * d).sum(-1)
        c = (o * o).sum(-1) - radius**2
        disc = b * b - c
        t = -b - torch.sqrt(disc.clamp_min(0))
        n = torch.nn.functional.normalize(o + t[..., None] * d, dim=-1)
        img = torch.where((disc > 0)[..., None], 0.5 + 0.5 * n, torch.ones(3))
        images.append(img)
    info = SceneInfo(
        aabb=torch.tensor([[-0.7] * 3, [0.7] * 3]),
        unbounded=False,
        background=torch.ones(3),
        near=0.05,
        far=4.0,
    )
    del invert_rigid
    return TrainData(torch.stack(images).float(), cams), info


def write_sphere_dataset(
    root: Path, n_train: int = 12, n_test: int = 3, size: int = 32, radius: float = 0.5
) -> Path:
    """The analytic sphere as a Blender-style dataset on disk: RGBA PNGs, transforms_{train,test}.json
    (OpenGL c2w), metric z-depth EXRs and the ground-truth mesh (`gt_mesh_path`)."""
    import cv2
    import torch
    import trimesh

    from recon.cameras import camera_rays
    from recon.cameras.conventions import opengl_c2w_from_opencv_c2w
    from recon.io.exr import write_depth_exr

    data, _ = sphere_scene(n_cams=n_train + n_test, size=size, radius=radius)
    root.mkdir(parents=True, exist_ok=True)
    trimesh.creation.icosphere(subdivisions=4, radius=radius).export(root / "mesh.ply")
    f = float(data.cameras.K[0, 0, 0])
    for split, ids in (("train", range(n_train)), ("test", range(n_train, n_train + n_test))):
        (root / split).mkdir(exist_ok=True)
        frames = []
        for k, i in enumerate(ids):
            o, d, z = camera_rays(data.cameras, i)
            b = (o * d).sum(-1)
            disc = b * b - ((o * o).sum(-1) - radius**2)
            t = -b - torch.sqrt(disc.clamp_min(0))
            hit = disc > 0
            rgba = torch.cat([data.images[i], hit[..., None].float()], -1).numpy()
            rgba[..., :3] = np.where(hit[..., None].numpy(), rgba[..., :3], 0)
            bgra = cv2.cvtColor((rgba * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGBA2BGRA)
            cv2.imwrite(str(root / split / f"r_{k}.png"), bgra)
            write_depth_exr(
                root / split / f"r_{k}_depth.exr",
                torch.where(hit, t * z, 0).numpy().astype(np.float32),
            )
            c2w = opengl_c2w_from_opencv_c2w(data.cameras.world_from_cam[i].double().numpy())
            frames.append(
                {
                    "file_path": f"./{split}/r_{k}",
                    "depth_file_path": f"{split}/r_{k}_depth.exr",
                    "transform_matrix": c2w.tolist(),
                }
            )
        meta = {
            "fl_x": f,
            "fl_y": f,
            "cx": size / 2,
            "cy": size / 2,
            "w": size,
            "h": size,
            "gt_mesh_path": "mesh.ply",
            "frames": frames,
        }
        (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return root


def sphere_workspace(root: Path, n_train: int = 6, n_test: int = 1, size: int = 24) -> Path:
    """`recon sfm --from-transforms` on the analytic sphere dataset: a workspace ready to train."""
    data = write_sphere_dataset(root / "sphere", n_train=n_train, n_test=n_test, size=size)
    recon_cli("sfm", "--from-transforms", str(data), "-w", str(root / "ws"))
    return root / "ws"
