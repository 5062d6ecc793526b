"""recon's packed splat layout for its 3D viewer: ~16 bytes a Gaussian at SH degree 3, read
back exactly as the viewer (`recon/eval/viewer.js`) decodes it.

The compressed PLY's scheme (PlayCanvas; `splat_formats`) with fewer bits where a render
does not show them, and the view-dependent colour vector-quantised as in compact 3DGS work
(Niedermayr et al. 2024, "Compressed 3D Gaussian Splatting", Sec. 4.1: k-means codebooks of
the SH coefficients; Lee et al. 2024 likewise): the Gaussians in Morton order, cut into chunks
of 256 with the compressed PLY's 18 float32 bounds each; per Gaussian
    position 11-10-11 bit fractions of the chunk's box (4 bytes),
    rotation "smallest three" at 7-7-8 bits under its 2-bit index (3 bytes),
    log-scale 8-bit fractions of the chunk's range (3 bytes),
    DC colour 8-bit fractions of the chunk's range and opacity sigmoid 8-bit (4 bytes),
    the index of its SH bands 1..degree in a codebook of `CODEBOOK` entries (2 bytes),
each stored as byte planes (every Gaussian's first byte, then every second byte...) so that
gzip finds what repeats; then the codebook as 8-bit fractions of each coefficient's range.
The whole is gzip-compressed (`gzip.compress`; the browser's `DecompressionStream`).
"""

from __future__ import annotations

import gzip

import numpy as np
import torch

from recon.gaussians.splat_formats import (
    CHUNK,
    SH_C0,
    _pack_111011,
    _unorm,
    _unpack_111011,
    logit,
    morton_order,
    pack_rotation,
    sigmoid,
    unpack_rotation,
)

CODEBOOK = 1024  # SH codebook entries (fewer when there are fewer Gaussians)
ROTATION_BITS = (7, 7, 8)  # the three smaller quaternion components, under a 2-bit index
KMEANS_SAMPLE = 50_000  # Gaussians the codebook is fitted to (all of them are then assigned)
KMEANS_ITERATIONS = 8


def sh_codebook(
    values: np.ndarray, size: int, seed: int = 0, sample: int = KMEANS_SAMPLE
) -> tuple[np.ndarray, np.ndarray]:
    """k-means (Lloyd's iterations from `size` distinct rows drawn at random) of rows (G, D):
    -> codebook (K, D) float64 and every row's nearest entry (G,) int64, K = min(size, G).
    Fitted to at most `sample` rows, then every row assigned; an entry no row picks keeps its
    start."""
    x = torch.from_numpy(np.asarray(values, np.float32))
    g = torch.Generator().manual_seed(seed)
    fit = x[torch.randperm(len(x), generator=g)[:sample]] if len(x) > sample else x
    k = min(size, len(fit))
    centres = fit[torch.randperm(len(fit), generator=g)[:k]].clone()

    def nearest(rows: torch.Tensor) -> torch.Tensor:
        # |x - c|^2 = |x|^2 - 2 x.c + |c|^2; |x|^2 does not change the argmin
        return torch.cat(
            [
                ((centres * centres).sum(1)[None] - 2 * rows[i : i + 16384] @ centres.T).argmin(1)
                for i in range(0, len(rows), 16384)
            ]
        )

    for _ in range(KMEANS_ITERATIONS):
        labels = nearest(fit)
        sums = torch.zeros_like(centres).index_add_(0, labels, fit)
        counts = torch.bincount(labels, minlength=k).float()[:, None]
        centres = torch.where(counts > 0, sums / counts.clamp(min=1), centres)
    return centres.double().numpy(), nearest(x).numpy().astype(np.int64)


def _fraction(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """values (G, n) as fractions of [lo, hi] (G, n); 0 where the range is empty (< 1e-5)."""
    span = hi - lo
    return np.where(span > 1e-5, np.clip((values - lo) / np.where(span > 1e-5, span, 1), 0, 1), 0)


def _planes(words: np.ndarray, n_bytes: int) -> np.ndarray:
    """(G,) unsigned integers -> (n_bytes, G) uint8, the low byte first."""
    w = np.asarray(words, np.uint64)
    return np.stack(
        [((w >> np.uint64(8 * b)) & np.uint64(255)).astype(np.uint8) for b in range(n_bytes)]
    )


def _words(planes: np.ndarray) -> np.ndarray:
    return sum(planes[b].astype(np.uint64) << np.uint64(8 * b) for b in range(len(planes)))


def pack_splats(
    means: np.ndarray,
    quats: np.ndarray,
    log_scales: np.ndarray,
    opacity_logits: np.ndarray,
    sh: np.ndarray,
    codebook: int = CODEBOOK,
    seed: int = 0,
) -> tuple[dict, bytes]:
    """Gaussians (means (G, 3), quats wxyz (G, 4), log_scales (G, 3), opacity_logits (G,),
    sh (G, K, 3)) -> (header: count, sh_bases, codebook size and each section's [offset,
    length] in the decompressed bytes; the gzip-compressed bytes). See the module docstring."""
    G, K = sh.shape[:2]
    order = morton_order(np.asarray(means, np.float64))
    chunk_of = np.arange(G) // CHUNK
    n_chunks = int(chunk_of[-1]) + 1 if G else 0

    def bounds(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        v = np.asarray(values, np.float64)[order]
        lo = np.full((n_chunks, v.shape[1]), np.inf)
        hi = np.full((n_chunks, v.shape[1]), -np.inf)
        np.minimum.at(lo, chunk_of, v)
        np.maximum.at(hi, chunk_of, v)
        return v, lo, hi

    pos, pos_lo, pos_hi = bounds(means)
    scl, scl_lo, scl_hi = bounds(np.clip(log_scales, -20, 20))
    rgb, rgb_lo, rgb_hi = bounds(0.5 + SH_C0 * np.asarray(sh[:, 0], np.float64))
    chunks = np.concatenate([pos_lo, pos_hi, scl_lo, scl_hi, rgb_lo, rgb_hi], 1).astype("<f4")
    # fractions of the float32 bounds the viewer reads
    c = chunks.astype(np.float64)[chunk_of]
    t_pos = _fraction(pos, c[:, 0:3], c[:, 3:6])
    sections = {
        "chunks": chunks.tobytes(),
        "position": _planes(_pack_111011(t_pos), 4),
        "rotation": _planes(pack_rotation(np.asarray(quats)[order], ROTATION_BITS), 3),
        "scale": _unorm(_fraction(scl, c[:, 6:9], c[:, 9:12]), 8).T.astype(np.uint8),
        "colour": np.concatenate(
            [
                _unorm(_fraction(rgb, c[:, 12:15], c[:, 15:18]), 8).T,
                _unorm(sigmoid(np.asarray(opacity_logits, np.float64)[order]), 8)[None],
            ]
        ).astype(np.uint8),
    }
    size = 0
    if K > 1:
        rest = np.asarray(sh, np.float64)[order, 1:].reshape(G, -1)  # (G, (K - 1) 3)
        entries, labels = sh_codebook(rest, codebook, seed)
        lo, hi = entries.min(0), entries.max(0)
        sections["sh_labels"] = _planes(labels, 2)
        sections["sh_range"] = np.concatenate([lo, hi]).astype("<f4").tobytes()
        sections["sh_codebook"] = _unorm(_fraction(entries, lo, hi), 8).astype(np.uint8)
        size = len(entries)
    header = {"count": int(G), "sh_bases": int(K), "codebook": size, "sections": {}}
    parts, offset = [], 0
    for name, value in sections.items():
        raw = value if isinstance(value, bytes) else np.ascontiguousarray(value).tobytes()
        header["sections"][name] = [offset, len(raw)]
        parts.append(raw)
        offset += len(raw)
    return header, gzip.compress(b"".join(parts), compresslevel=9, mtime=0)


def unpack_splats(header: dict, data: bytes) -> dict[str, np.ndarray]:
    """`pack_splats`' output -> means, quats (wxyz), log_scales, opacity_logits, sh (G, K, 3)
    in the pack's (Morton) order, decoded as the viewer decodes them."""
    raw = gzip.decompress(data)
    G, K = header["count"], header["sh_bases"]

    def section(name: str, dtype=np.uint8) -> np.ndarray:
        offset, length = header["sections"][name]
        return np.frombuffer(raw, dtype, length // np.dtype(dtype).itemsize, offset)

    c = section("chunks", "<f4").astype(np.float64).reshape(-1, 18)[np.arange(G) // CHUNK]
    t_pos = _unpack_111011(_words(section("position").reshape(4, G)).astype(np.uint32))
    t_scale = section("scale").reshape(3, G).T / 255.0
    colour = section("colour").reshape(4, G).T / 255.0
    rgb = c[:, 12:15] * (1 - colour[:, :3]) + c[:, 15:18] * colour[:, :3]
    sh = np.zeros((G, K, 3))
    sh[:, 0] = (rgb - 0.5) / SH_C0
    if K > 1:
        labels = _words(section("sh_labels").reshape(2, G)).astype(np.int64)
        D = 3 * (K - 1)
        lo, hi = np.split(section("sh_range", "<f4").astype(np.float64), 2)
        entries = lo + section("sh_codebook").reshape(-1, D) / 255.0 * (hi - lo)
        sh[:, 1:] = entries[labels].reshape(G, K - 1, 3)
    return {
        "means": (c[:, 0:3] * (1 - t_pos) + c[:, 3:6] * t_pos).astype(np.float32),
        "quats": unpack_rotation(
            _words(section("rotation").reshape(3, G)).astype(np.uint32), ROTATION_BITS
        ).astype(np.float32),
        "log_scales": (c[:, 6:9] * (1 - t_scale) + c[:, 9:12] * t_scale).astype(np.float32),
        "opacity_logits": logit(colour[:, 3]).astype(np.float32),
        "sh": sh.astype(np.float32),
    }


def script_string(data: bytes) -> bytes:
    """`data` as the body of a JavaScript string literal in a script the page loads with
    charset="x-user-defined" (the WHATWG encoding that maps every byte to one character,
    0x80-0xFF to U+F780-U+F7FF): each byte itself, but for the four a literal must escape
    (backslash, double quote, line feed, carriage return). ~1.6 % over the bytes, where
    base64 adds 33 %."""
    escapes = {0x5C: b"\\\\", 0x22: b'\\"', 0x0A: b"\\n", 0x0D: b"\\r"}
    out = bytearray()
    start = 0
    arr = np.frombuffer(data, np.uint8)
    for i in np.flatnonzero(np.isin(arr, list(escapes))):
        out += data[start:i] + escapes[int(arr[i])]
        start = i + 1
    out += data[start:]
    return bytes(out)
