"""VLAD retrieval for pair selection: each math step against a brute-force twin or a case
worked by hand, and the whole on sample_data's photos against the verified pairs of
exhaustive matching."""

from __future__ import annotations

import numpy as np
import torch

from recon.sfm.retrieval import (
    global_descriptors,
    kmeans,
    nearest_pairs,
    nearest_word,
    retrieval_pairs,
    root_sift,
    vlad,
)


def test_root_sift_is_the_square_root_of_the_l1_normalised_descriptor():
    d = np.array([[1, 3, 0, 0], [0, 0, 0, 0]], dtype=np.uint8)
    r = root_sift(d)
    np.testing.assert_allclose(r[0], [0.5, np.sqrt(0.75), 0, 0], rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(r[0]), 1.0, rtol=1e-6)  # Hellinger: unit L2
    assert r.dtype == np.float32 and not r[1].any()


def test_nearest_word_matches_brute_force_distances():
    g = torch.Generator().manual_seed(0)
    x, words = torch.randn(200, 16, generator=g), torch.randn(9, 16, generator=g)
    brute = torch.cdist(x, words).argmin(dim=1)
    assert torch.equal(nearest_word(x, words), brute)


def test_kmeans_finds_well_separated_clusters():
    rng = np.random.default_rng(1)
    truth = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]], dtype=np.float32)
    x = np.concatenate([c + 0.1 * rng.standard_normal((50, 2)) for c in truth]).astype(np.float32)
    centres = kmeans(x, 3, iterations=10, seed=0)
    for c in truth:  # each true centre has a found centre within the clusters' spread
        assert np.linalg.norm(centres - c, axis=1).min() < 0.1


def test_vlad_by_hand():
    """Two words at (0, 0) and (4, 0); descriptors (1, 0), (0, 2) -> word 0, (5, 1) -> word 1.
    Residual sums (1, 2) and (1, 1), each unit-normalised, then the whole vector."""
    words = np.array([[0.0, 0.0], [4.0, 0.0]], dtype=np.float32)
    x = np.array([[1.0, 0.0], [0.0, 2.0], [5.0, 1.0]], dtype=np.float32)
    v = vlad(x, words)
    expected = np.concatenate([np.array([1, 2]) / np.sqrt(5), np.array([1, 1]) / np.sqrt(2)])
    np.testing.assert_allclose(v, expected / np.sqrt(2), rtol=1e-6)
    assert not vlad(np.zeros((0, 2), np.float32), words).any()  # no descriptors: zero vector


def test_nearest_pairs_keeps_each_images_k_most_similar():
    s = np.array(
        [
            [1.0, 0.9, 0.1, 0.2],
            [0.9, 1.0, 0.3, 0.1],
            [0.1, 0.3, 1.0, 0.8],
            [0.2, 0.1, 0.8, 1.0],
        ]
    )
    assert nearest_pairs(s, 1) == [(0, 1), (2, 3)]
    assert nearest_pairs(s, 2) == [(0, 1), (0, 3), (1, 2), (2, 3)]
    assert len(nearest_pairs(s, 10)) == 6  # k above I - 1: every pair


def test_images_sharing_descriptors_are_retrieved_together():
    """Three "places", four images each, every image a noisy subset of its place's
    descriptors: each image's 3 nearest are the other images of its place."""
    rng = np.random.default_rng(2)
    places = [rng.integers(0, 255, (400, 128)) for _ in range(3)]
    names, descriptors = [], []
    for p, place in enumerate(places):
        for i in range(4):
            keep = place[rng.choice(400, 250, replace=False)]
            descriptors.append(np.clip(keep + rng.integers(-8, 9, keep.shape), 0, 255))
            names.append(f"p{p}_{i}")
    pairs = retrieval_pairs(names, descriptors, k=3)
    assert all(a[:2] == b[:2] for a, b in pairs)
    assert len(pairs) == 3 * 6  # all pairs within each place, none across
    v = global_descriptors(descriptors)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, rtol=1e-5)
