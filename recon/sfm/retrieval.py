"""Image retrieval for pair selection: which photos of an unordered folder are worth matching.

Exhaustive matching costs N (N - 1) / 2 pairs; most of them see different parts of the scene
and fail verification (fox: 889 of 2211 pairs verify). Each image is summarised by one
global descriptor built from its own SIFT descriptors, and matched only with the images whose
descriptors are most similar — COLMAP's vocabulary-tree matching (Schönberger et al. 2016,
"A Vote-and-Verify Strategy for Fast Spatial Verification in Image Retrieval") without a
pre-trained tree, which recon cannot download:

- RootSIFT (Arandjelović & Zisserman 2012, "Three things everyone should know to improve
  object retrieval", Sec. 2): L1-normalise the descriptor, take the element-wise square root;
  Euclidean distance between RootSIFTs is the Hellinger kernel between the SIFTs.
- VLAD (Jégou et al. 2010, "Aggregating local descriptors into a compact image
  representation", Sec. 3): with K visual words c_k learned from the capture's own
  descriptors by k-means, v_k = sum over the image's descriptors x assigned to c_k of (x - c_k).
- Intra-normalisation (Arandjelović & Zisserman 2013, "All about VLAD", Sec. 3): each v_k
  L2-normalised on its own, so bursts of one repeated texture do not dominate, then the whole
  vector L2-normalised. The similarity of two images is the dot product of their vectors.

Pure numpy / torch on the CPU: no pycolmap here (`colmap_steps` reads the descriptors).
"""

from __future__ import annotations

import numpy as np
import torch

VLAD_WORDS = 64  # K: visual words; the VLAD vector has K x 128 entries
KMEANS_ITERATIONS = 10
KMEANS_SAMPLES_PER_IMAGE = 300  # descriptors per image the vocabulary is learned from


def root_sift(descriptors: np.ndarray) -> np.ndarray:
    """(N, 128) SIFT descriptors (any dtype, non-negative) -> (N, 128) float32 RootSIFT:
    sqrt(x / |x|_1), so every row has unit L2 norm (a zero row stays zero)."""
    x = descriptors.astype(np.float32)
    x /= np.maximum(x.sum(axis=1, keepdims=True), 1e-12)
    return np.sqrt(x)


def nearest_word(x: torch.Tensor, words: torch.Tensor) -> torch.Tensor:
    """(N, D) points, (K, D) centres -> (N,) index of the nearest centre (Euclidean):
    argmin |x - c|^2 = argmax (2 x.c - |c|^2), one matrix product."""
    return (2.0 * x @ words.T - (words * words).sum(dim=1)).argmax(dim=1)


def kmeans(x: np.ndarray, k: int, iterations: int, seed: int) -> np.ndarray:
    """(N, D) float32 points -> (k, D) centres by Lloyd's algorithm from k distinct random
    points (a centre that loses all its points keeps its place)."""
    rng = np.random.default_rng(seed)
    points = torch.from_numpy(x)
    centres = points[torch.from_numpy(rng.choice(len(x), size=k, replace=False))].clone()
    for _ in range(iterations):
        assigned = nearest_word(points, centres)
        sums = torch.zeros_like(centres).index_add_(0, assigned, points)
        counts = torch.bincount(assigned, minlength=k).to(points.dtype)[:, None]
        centres = torch.where(counts > 0, sums / counts.clamp_min(1.0), centres)
    return centres.numpy()


def vlad(descriptors: np.ndarray, words: np.ndarray) -> np.ndarray:
    """(N, D) descriptors of one image, (K, D) visual words -> (K * D,) intra-normalised,
    L2-normalised VLAD vector (zero for an image without descriptors)."""
    x, c = torch.from_numpy(descriptors), torch.from_numpy(words)
    residuals = torch.zeros_like(c)
    if len(x):
        assigned = nearest_word(x, c)
        residuals.index_add_(0, assigned, x - c[assigned])
    residuals /= residuals.norm(dim=1, keepdim=True).clamp_min(1e-12)
    v = residuals.flatten()
    return (v / v.norm().clamp_min(1e-12)).numpy()


def global_descriptors(descriptors: list[np.ndarray], seed: int = 0) -> np.ndarray:
    """Per-image (N_i, 128) SIFT descriptors -> (I, VLAD_WORDS * 128) VLAD vectors over RootSIFT,
    with a vocabulary learned from up to KMEANS_SAMPLES_PER_IMAGE descriptors of each image."""
    rooted = [root_sift(d) for d in descriptors]
    rng = np.random.default_rng(seed)
    sample = np.concatenate(
        [
            d[rng.choice(len(d), size=min(len(d), KMEANS_SAMPLES_PER_IMAGE), replace=False)]
            for d in rooted
        ]
    )
    words = kmeans(sample, min(VLAD_WORDS, len(sample)), KMEANS_ITERATIONS, seed)
    return np.stack([vlad(d, words) for d in rooted])


def nearest_pairs(similarity: np.ndarray, k: int) -> list[tuple[int, int]]:
    """(I, I) symmetric similarity -> sorted pairs (i, j), i < j: each image with its k most
    similar others (ties broken by index), so an image can end up in more than k pairs."""
    s = similarity.astype(np.float64, copy=True)
    np.fill_diagonal(s, -np.inf)
    k = min(k, len(s) - 1)
    pairs = set()
    for i, row in enumerate(s):
        for j in np.argsort(-row, kind="stable")[:k]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def retrieval_pairs(
    names: list[str], descriptors: list[np.ndarray], k: int, seed: int = 0
) -> list[tuple[str, str]]:
    """Image names with their (N_i, 128) SIFT descriptors -> the name pairs of `nearest_pairs`
    under VLAD similarity."""
    v = global_descriptors(descriptors, seed)
    return [(names[i], names[j]) for i, j in nearest_pairs(v @ v.T, k)]
