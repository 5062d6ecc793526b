"""Did SfM place enough of the photos? The `registration` section of the sfm report, and the
one-line warning `recon sfm` prints (and `recon train` repeats) when it only half worked."""

from __future__ import annotations

import re
from collections import Counter


def reason_kind(reason: str) -> str:
    """The cause of an unregistered photo without its numbers: the text before the first ':'
    or '(' of `colmap_diagnose.unregistered_reason`. Example: "too few matches: best partner
    image has 3 descriptor matches (512 keypoints); ..." -> "too few matches"."""
    return re.split(r"[:(]", reason, maxsplit=1)[0].strip()


def registration_summary(report: dict, min_registered: float) -> dict:
    """Registered photos against the usable ones (`images_registered`, `images_usable`,
    `unregistered` of the engine's report); `partial` when fewer than `min_registered` of
    them registered, with the commonest cause and how many photos it kept out."""
    usable, registered = int(report["images_usable"]), int(report["images_registered"])
    kinds = Counter(reason_kind(u["reason"]) for u in report.get("unregistered", []))
    commonest, count = kinds.most_common(1)[0] if kinds else ("", 0)
    example = next(
        (
            u["reason"]
            for u in report.get("unregistered", [])
            if reason_kind(u["reason"]) == commonest
        ),
        "",
    )
    fraction = registered / usable if usable else 0.0
    return {
        "usable": usable,
        "registered": registered,
        "fraction": round(fraction, 4),
        "min_registered": min_registered,
        "partial": fraction < min_registered,
        "commonest_reason": commonest,
        "commonest_reason_count": count,
        "commonest_reason_example": example,
    }


def partial_warning(summary: dict) -> str:
    """One line for the terminal. Example: "only 3 of 16 usable photos registered (19 %, below
    --min-registered 0.8); commonest reason, 11 photos: too few matches: best partner ..."."""
    line = (
        f"only {summary['registered']} of {summary['usable']} usable photos registered "
        f"({100 * summary['fraction']:.0f} %, below --min-registered {summary['min_registered']:g})"
    )
    if summary["commonest_reason_count"]:
        line += (
            f"; commonest reason, {summary['commonest_reason_count']} photos: "
            f"{summary['commonest_reason_example']}"
        )
    return line
