"""recon's packed splat layout: the k-means codebook, a round trip within each field's
quantisation step, and the script-string escaping the viewer reads back."""

import gzip
import itertools
import re

import numpy as np

from recon.gaussians.splat_formats import morton_order, unit_quats
from recon.gaussians.splat_pack import pack_splats, script_string, sh_codebook, unpack_splats
from tests.eval.test_viewer import random_gaussians


def test_kmeans_finds_two_clusters_and_keeps_rows_when_there_are_few():
    rng = np.random.default_rng(0)
    a, b = rng.normal(0, 0.01, (50, 4)), rng.normal(0, 0.01, (70, 4)) + 5.0
    entries, labels = sh_codebook(np.concatenate([a, b]), 2)
    assert sorted(np.bincount(labels).tolist()) == [50, 70]
    for rows in (a, b):
        centre = entries[labels[: len(a)][0] if rows is a else labels[-1]]
        np.testing.assert_allclose(centre, rows.mean(0), atol=1e-5)
    few = rng.normal(size=(5, 3))
    entries, labels = sh_codebook(few, 16)  # as many entries as rows: each its own
    np.testing.assert_allclose(entries[labels], few, atol=1e-6)


def test_a_round_trip_is_within_each_fields_step():
    g = random_gaussians(1000)
    header, data = pack_splats(**g)
    assert header["count"] == 1000 and header["codebook"] == 1000  # fewer rows than entries
    back = unpack_splats(header, data)
    order = morton_order(g["means"].astype(np.float64))
    # a chunk of 256 spans at most the whole box (1 wide): 11 / 10 bits of it
    assert np.abs(back["means"] - g["means"][order]).max() <= 1.0 / 1023
    # log-scales: 8 bits of a chunk's range (log 0.005 .. log 0.08, ~2.8)
    assert np.abs(back["log_scales"] - g["log_scales"][order]).max() <= 3.0 / 255
    q, r = unit_quats(g["quats"][order]), unit_quats(back["quats"])
    angle = 2 * np.arccos(np.clip(np.abs((q * r).sum(1)), 0, 1))
    assert np.degrees(angle).max() < 1.5  # 7-bit components
    opacity = 1 / (1 + np.exp(-g["opacity_logits"][order]))
    assert np.abs(1 / (1 + np.exp(-back["opacity_logits"])) - opacity).max() <= 0.5 / 255 + 1e-6
    sh = g["sh"][order]
    dc_range = np.ptp(sh[:, 0], 0).max()
    assert np.abs(back["sh"][:, 0] - sh[:, 0]).max() <= dc_range / 255
    rest_range = np.ptp(sh[:, 1:].reshape(1000, -1), 0).max()  # 8-bit codebook entries
    assert np.abs(back["sh"][:, 1:] - sh[:, 1:]).max() <= 0.5 * rest_range / 255 + 1e-5


def test_degree_zero_has_no_codebook_and_sections_tile_the_bytes():
    g = random_gaussians(300)
    header, data = pack_splats(**{**g, "sh": g["sh"][:, :1]})
    assert header["codebook"] == 0 and "sh_labels" not in header["sections"]
    spans = sorted(header["sections"].values())
    assert spans[0][0] == 0 and all(a + n == b for (a, n), (b, _) in itertools.pairwise(spans))
    assert sum(n for _, n in spans) == len(gzip.decompress(data))
    # 18 floats a chunk of 256; 4 + 3 + 3 + 4 bytes a Gaussian
    assert header["sections"]["chunks"][1] == 2 * 18 * 4
    assert len(gzip.decompress(data)) == 2 * 18 * 4 + 300 * 14
    assert unpack_splats(header, data)["sh"].shape == (300, 1, 3)


def test_the_script_string_escapes_exactly_what_a_literal_must():
    data = bytes(range(256)) * 3
    body = script_string(data)
    assert len(body) == len(data) + 4 * 3
    assert b"\n" not in body and b"\r" not in body
    assert re.search(rb'(?<!\\)"', body.replace(b"\\\\", b"")) is None  # every quote escaped
    unescape = {b"n": b"\n", b"r": b"\r", b'"': b'"', b"\\": b"\\"}
    back = re.sub(rb"\\(.)", lambda m: unescape[m.group(1)], body, flags=re.DOTALL)
    assert back == data
