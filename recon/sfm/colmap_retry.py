"""Targeted retries: give the photos that did not register richer features and more match
partners, without redoing the work for the photos that did.

A retry starts from a copy of the previous attempt's database. Only the images left out get
new keypoints (more, finer, lower-contrast SIFT) and are matched against every other image;
the matches between registered images are kept. On a 67-photo capture with 3 photos out this
costs ~3 x 67 pairs instead of re-extracting and re-matching all 2211 pairs at 16k features.
"""

from __future__ import annotations

import sqlite3
import zlib  # noqa: F401  (before pycolmap: importing pycolmap first corrupts zlib's heap)
from pathlib import Path

import pycolmap

from recon.sfm.colmap_steps import exhaustive_pairs, sequential_pairs

RETRY_EXHAUSTIVE_MAX_IMAGES = 300  # above this a retried image meets only its sequence neighbours


def copy_database(source: Path, target: Path) -> None:
    """Consistent copy of a COLMAP database, including pages still in its write-ahead log
    (a plain file copy of database.db can miss them)."""
    target.unlink(missing_ok=True)
    with sqlite3.connect(source) as src, sqlite3.connect(target) as dst:
        src.backup(dst)
    src.close()
    dst.close()


def image_ids(database: Path) -> dict[str, int]:
    db = pycolmap.Database.open(database)
    try:
        return {im.name: im.image_id for im in db.read_all_images()}
    finally:
        db.close()


def forget_matches(database: Path, names: list[str]) -> None:
    """Delete every match and two-view geometry that involves one of `names`."""
    ids = image_ids(database)
    forget = {ids[n] for n in names if n in ids}
    db = pycolmap.Database.open(database)
    try:
        for a in forget:
            for b in ids.values():
                if a != b and (b not in forget or a < b):
                    db.delete_matches(a, b)
                    db.delete_two_view_geometry(a, b)
    finally:
        db.close()


def forget_features(database: Path, names: list[str]) -> None:
    """Delete the keypoints, descriptors and matches of `names`, keeping their image and
    camera rows: COLMAP's extractor then re-extracts exactly those images (it skips images
    that already have both keypoints and descriptors). pycolmap has no per-image delete for
    features, so this one step uses COLMAP's SQLite tables (`keypoints`, `descriptors`,
    keyed by `image_id`) directly."""
    forget_matches(database, names)
    ids = image_ids(database)
    rows = [(ids[n],) for n in names if n in ids]
    with sqlite3.connect(database) as con:
        con.executemany("DELETE FROM keypoints WHERE image_id = ?", rows)
        con.executemany("DELETE FROM descriptors WHERE image_id = ?", rows)
    con.close()


def retry_pairs(names: list[str], retry: list[str], all_pairs: bool) -> list[tuple[str, str]]:
    """Pairs to match in a retry: every pair that involves a retried image (its sequence
    neighbourhood only, overlap 20, beyond RETRY_EXHAUSTIVE_MAX_IMAGES photos), or with
    `all_pairs` every pair of the set (pairs already in the database are skipped by COLMAP)."""
    small = len(names) <= RETRY_EXHAUSTIVE_MAX_IMAGES
    if all_pairs and small:
        return exhaustive_pairs(names)
    wanted = set(retry)
    candidates = exhaustive_pairs(names) if small else sequential_pairs(names, overlap=20)
    return [(a, b) for a, b in candidates if a in wanted or b in wanted]
