"""The SfM report: plain JSON saying what went in, what registered, what did not and why,
how good the model is, what each attempt did, and where the time went."""

from __future__ import annotations

import zlib  # noqa: F401  (before pycolmap: importing pycolmap first corrupts zlib's heap)
from dataclasses import asdict
from typing import TYPE_CHECKING

import pycolmap

from recon.sfm import colmap_diagnose as diagnose
from recon.sfm.photos import PhotoSet

if TYPE_CHECKING:
    from recon.sfm.colmap_config import SfmConfig
    from recon.sfm.colmap_steps import Attempt, PhaseTimer


def determinism_note(num_threads: int) -> str:
    """What a fixed seed pins down (tests/sfm/test_colmap_sfm.py runs the same photos twice)."""
    return (
        "Features, matches and two-view geometries repeat exactly at any thread count (image "
        "ids follow the photos' names) and the incremental mapper runs on one thread, so the "
        "same photos and seed register the same photos with the same poses"
        + (
            "; the final bundle adjustment and the undistortion use "
            f"{num_threads} threads and may differ in the last digits (fox: up to 2e-7 in a "
            "pose entry)."
            if num_threads != 1
            else " bit for bit (num_threads=1)."
        )
    )


def models_summary(attempt: Attempt) -> dict:
    sizes = sorted((m.num_reg_images() for m in attempt.models.values()), reverse=True)
    summary = {"count": len(sizes), "registered_per_model": sizes}
    if len(sizes) > 1:
        summary["note"] = (
            f"COLMAP produced {len(sizes)} separate models; the largest ({sizes[0]} images) was "
            "kept, images only in the others are listed as unregistered"
        )
    return summary


def unregistered_images(attempt: Attempt, photos: PhotoSet) -> list[dict]:
    """Every usable photo not in the kept model, with the reason read from the database."""
    kept = attempt.best
    registered = diagnose.registered_names(kept) if kept is not None else set()
    others = sorted(
        (m for m in attempt.models.values() if m is not kept), key=lambda m: -m.num_reg_images()
    )
    other_model = {
        name: k for k, m in enumerate(others, start=2) for name in diagnose.registered_names(m)
    }
    min_inliers = attempt.options.min_num_inliers
    stats = diagnose.image_match_stats(attempt.database, min_inliers)
    return [
        {
            "name": name,
            "reason": diagnose.unregistered_reason(
                stats.get(name), min_inliers, other_model.get(name)
            ),
        }
        for name in photos.names
        if name not in registered
    ]


def attempt_summary(index: int, attempt: Attempt, num_images: int) -> dict:
    return {
        "attempt": index,
        "name": attempt.options.name,
        "options": asdict(attempt.options),
        "registered": attempt.registered,
        "points3d": attempt.best.num_points3D() if attempt.models else 0,
        "retried_images": attempt.retried,
        "pairs_matched": attempt.pairs_matched,
        "max_pair_parallax_deg": attempt.max_pair_parallax,
        "models": models_summary(attempt),
        "registered_all": attempt.registered == num_images,
        **attempt.timer.as_dict(),
    }


def build_report(
    config: SfmConfig,
    photos: PhotoSet,
    attempts: list[Attempt],
    chosen: Attempt,
    reconstruction: pycolmap.Reconstruction,
    timer: PhaseTimer,
) -> dict:
    n = len(photos.photos)
    unregistered = unregistered_images(chosen, photos)
    return {
        "pycolmap_version": pycolmap.__version__,
        "config": asdict(config),
        "images_given": n + len(photos.skipped),
        "images_usable": n,
        "images_registered": chosen.registered,
        "skipped": [{"name": name, "reason": reason} for name, reason in photos.skipped],
        "converted": [
            {"name": p.name, "source": p.source.name, "reason": p.converted}
            for p in photos.photos
            if p.converted
        ],
        "unregistered": unregistered,
        "models": models_summary(chosen),
        **diagnose.model_stats(chosen.best),
        "cameras_before_undistortion": diagnose.camera_summary(chosen.best),
        "cameras": diagnose.camera_summary(reconstruction),
        "attempts": [attempt_summary(i, a, n) for i, a in enumerate(attempts, start=1)],
        "chosen_attempt": attempts.index(chosen) + 1,
        "phases": timer.as_dict(),
        "determinism": determinism_note(config.num_threads),
    }
