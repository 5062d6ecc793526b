"""The two compact splat layouts web viewers share scenes in, written and read back exactly as
the viewers decode them.

`.splat` (antimatter15's WebGL viewer, read by SuperSplat, PlayCanvas, Babylon.js, Spark...):
32 bytes per Gaussian, no header, little-endian:
    position xyz float32 | scale xyz float32 (linear, exp of the log-scales) |
    colour RGBA uint8 (RGB = 255 (0.5 + C0 f_dc), A = 255 sigmoid(opacity)) |
    quaternion uint8 x 4 (w, x, y, z of the unit quaternion, 128 q + 128).
Degree-0 colour only: view-dependent SH bands are dropped.

Compressed PLY (PlayCanvas / SuperSplat, "splat-transform"): the Gaussians in Morton order, cut
into chunks of 256; per chunk 18 float32 bounds (min / max of position, of log-scale and of the
DC colour 0.5 + C0 f_dc); per Gaussian four uint32:
    position and log-scale 11-10-11 bit fractions of their chunk's range (x in the top bits),
    rotation "smallest three": 2 bits naming the largest |component| of (w, x, y, z) (made
    positive), then the other three in order, 10 bits each, as q sqrt(2)/2 + 1/2,
    colour RGBA8 (R in the top byte): DC colour as a fraction of the chunk's range, A = sigmoid,
and, with SH bands kept, one uint8 per f_rest coefficient (channel-major, as the INRIA PLY) as
(f / 8 + 1/2) 256, truncated. 16 bytes per Gaussian plus 3 per SH coefficient.

C0 = 1 / (2 sqrt(pi)), the degree-0 real SH basis constant (Kerbl et al. 2023 store colour as
SH coefficients; the viewers convert the DC term to a base colour with it).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

SH_C0 = 0.28209479177387814
CHUNK = 256
CHUNK_PROPS = [
    *(f"{m}_{a}" for m in ("min", "max") for a in "xyz"),
    *(f"{m}_scale_{a}" for m in ("min", "max") for a in "xyz"),
    *(f"{m}_{c}" for m in ("min", "max") for c in "rgb"),
]
VERTEX_PROPS = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


def logit(p: np.ndarray, bound: float = 40.0) -> np.ndarray:
    """Inverse sigmoid, +-bound at p = 1 and 0 (as the viewers decode a saturated alpha)."""
    with np.errstate(divide="ignore"):
        return np.clip(np.log(p) - np.log1p(-p), -bound, bound)


def unit_quats(quats: np.ndarray) -> np.ndarray:
    """(G, 4) -> (G, 4) unit quaternions; a zero quaternion becomes the identity."""
    q = np.asarray(quats, np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(norm > 0, q / np.where(norm > 0, norm, 1), np.array([1.0, 0, 0, 0]))


# ---------------------------------------------------------------------------------- .splat


def write_dot_splat(
    path: str | Path,
    means: np.ndarray,
    quats: np.ndarray,
    log_scales: np.ndarray,
    opacity_logits: np.ndarray,
    sh_dc: np.ndarray,
) -> None:
    """means (G, 3), quats (G, 4) wxyz, log_scales (G, 3), opacity_logits (G,), sh_dc (G, 3)
    -> `path` in the 32-byte .splat layout, most visible first (exp(sum of log-scales) times
    opacity, descending, as the viewer's own converter orders them)."""
    G = len(means)
    order = np.argsort(-np.exp(log_scales.sum(1)) * sigmoid(opacity_logits), kind="stable")
    record = np.zeros(
        G, dtype=[("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)]
    )
    record["pos"] = means[order]
    record["scale"] = np.exp(log_scales[order])
    rgb = 0.5 + SH_C0 * sh_dc[order]
    alpha = sigmoid(opacity_logits[order])[:, None]
    record["rgba"] = np.clip(np.rint(255 * np.concatenate([rgb, alpha], 1)), 0, 255)
    record["rot"] = np.clip(np.rint(128 * unit_quats(quats[order]) + 128), 0, 255)
    Path(path).write_bytes(record.tobytes())


def read_dot_splat(path: str | Path) -> dict[str, np.ndarray]:
    """A .splat file -> means, quats (wxyz, unit), log_scales, opacity_logits, sh (G, 1, 3),
    decoded as the viewer decodes them."""
    raw = Path(path).read_bytes()
    if len(raw) % 32:
        raise ValueError(f"{path}: {len(raw)} bytes is not a whole number of 32-byte splats")
    record = np.frombuffer(
        raw, dtype=[("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)]
    )
    rgba = record["rgba"].astype(np.float64) / 255
    return {
        "means": record["pos"].astype(np.float32),
        "quats": unit_quats((record["rot"].astype(np.float64) - 128) / 128).astype(np.float32),
        "log_scales": np.log(record["scale"].astype(np.float64)).astype(np.float32),
        "opacity_logits": logit(rgba[:, 3]).astype(np.float32),
        "sh": ((rgba[:, None, :3] - 0.5) / SH_C0).astype(np.float32),
    }


# ---------------------------------------------------------------------- compressed PLY


def morton_order(points: np.ndarray) -> np.ndarray:
    """Indices sorting (G, 3) points along a 3D Morton (Z-order) curve of 10 bits per axis
    over their bounding box: neighbours in the order are near in space, so each chunk of 256
    spans a small box and its 11-bit fractions are fine."""
    lo, hi = points.min(0), points.max(0)
    cells = ((points - lo) / np.where(hi > lo, hi - lo, 1) * 1023).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((cells[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(
                3 * bit + 2 - axis
            )
    return np.argsort(code, kind="stable")


def _unorm(t: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    return np.clip(np.floor(t * top + 0.5), 0, top).astype(np.uint32)


def _fractions(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """values (C, 256, 3) as fractions of their chunk's [lo, hi] (C, 3); 0 where the range is
    empty (below 1e-5, as the viewer's writer)."""
    span = hi - lo
    t = (values - lo[:, None]) / np.where(span > 1e-5, span, 1)[:, None]
    return np.where(span[:, None] > 1e-5, np.clip(t, 0, 1), 0)


def _pack_111011(t: np.ndarray) -> np.ndarray:
    return _unorm(t[..., 0], 11) << 21 | _unorm(t[..., 1], 10) << 11 | _unorm(t[..., 2], 11)


def _unpack_111011(bits: np.ndarray) -> np.ndarray:
    return np.stack(
        [(bits >> 21) / 2047.0, ((bits >> 11) & 0x3FF) / 1023.0, (bits & 0x7FF) / 2047.0], -1
    )


def pack_rotation(quats: np.ndarray, widths: tuple[int, int, int] = (10, 10, 10)) -> np.ndarray:
    """(G, 4) wxyz -> (G,) uint32 "smallest three": the index of the largest |component|
    above the rest, then the other three (sign chosen so the largest is positive) as
    q sqrt(2)/2 + 1/2 in order, on `widths` bits each (the compressed PLY's 10-10-10: 32 bits).
    """
    q = unit_quats(quats)
    largest = np.abs(q).argmax(1)
    q = q * np.where(q[np.arange(len(q)), largest] < 0, -1.0, 1.0)[:, None]
    out = largest.astype(np.uint32)
    slot = np.zeros(len(q), np.int64)  # which of the three a component of row g is
    for i in range(4):
        keep = largest != i
        width = np.asarray(widths)[np.minimum(slot, 2)]
        top = (1 << width) - 1
        value = np.clip(np.floor((q[:, i] * np.sqrt(0.5) + 0.5) * top + 0.5), 0, top)
        out = np.where(keep, (out << width.astype(np.uint32)) | value.astype(np.uint32), out)
        slot += keep
    return out.astype(np.uint32)


def unpack_rotation(bits: np.ndarray, widths: tuple[int, int, int] = (10, 10, 10)) -> np.ndarray:
    """Inverse of `pack_rotation`: (G,) uint32 -> (G, 4) wxyz (unit to the quantisation)."""
    bits = np.asarray(bits, np.uint32)
    shifts = (widths[1] + widths[2], widths[2], 0)
    three = np.stack(
        [((bits >> s) & ((1 << w) - 1)) / ((1 << w) - 1) for s, w in zip(shifts, widths)], -1
    )
    three = (three - 0.5) * np.sqrt(2.0)
    largest = (bits >> sum(widths)).astype(np.int64)
    m = np.sqrt(np.clip(1.0 - (three**2).sum(1), 0, None))
    q = np.empty((len(bits), 4))
    for mode in range(4):
        rows = largest == mode
        others = [i for i in range(4) if i != mode]
        q[np.ix_(rows, others)] = three[rows]
        q[rows, mode] = m[rows]
    return q


def compress_splats(
    means: np.ndarray,
    quats: np.ndarray,
    log_scales: np.ndarray,
    opacity_logits: np.ndarray,
    sh: np.ndarray,
) -> dict[str, np.ndarray]:
    """The compressed layout's arrays (see the module docstring): "order" (G,) the Morton
    order the rows follow, "chunks" (C, 18) float32 bounds, "packed" (G, 4) uint32 and
    "sh_rest" (G, 3 (K - 1)) uint8. means (G, 3), quats (G, 4) wxyz, log_scales (G, 3),
    opacity_logits (G,), sh (G, K, 3) with K in {1, 4, 9, 16}."""
    G, K = sh.shape[:2]
    if K not in (1, 4, 9, 16):
        raise ValueError(f"SH with {K} coefficients per channel: expected 1, 4, 9 or 16")
    order = morton_order(np.asarray(means, np.float64))
    chunks = -(-G // CHUNK)
    pad = np.concatenate([order, np.full(chunks * CHUNK - G, order[-1])])  # last one repeated

    def chunked(a):
        return np.asarray(a, np.float64)[pad].reshape(chunks, CHUNK, -1)

    pos, scl = chunked(means), np.clip(chunked(log_scales), -20, 20)
    rgb = 0.5 + SH_C0 * chunked(sh[:, 0])
    bounds = [(x.min(1), x.max(1)) for x in (pos, scl, rgb)]
    chunk_data = np.concatenate([b for pair in bounds for b in pair], 1).astype("<f4")
    rgb_t = _fractions(rgb, *bounds[2])
    alpha = sigmoid(chunked(opacity_logits)[..., 0])
    colour = (
        _unorm(rgb_t[..., 0], 8) << 24
        | _unorm(rgb_t[..., 1], 8) << 16
        | _unorm(rgb_t[..., 2], 8) << 8
        | _unorm(alpha, 8)
    )
    packed = np.stack(
        [
            _pack_111011(_fractions(pos, *bounds[0])),
            pack_rotation(np.asarray(quats)[pad]).reshape(chunks, CHUNK),
            _pack_111011(_fractions(scl, *bounds[1])),
            colour,
        ],
        -1,
    ).reshape(-1, 4)[:G]
    rest = np.transpose(np.asarray(sh, np.float64)[order, 1:], (0, 2, 1)).reshape(G, -1)
    rest_bytes = np.clip(np.trunc((rest / 8 + 0.5) * 256), 0, 255).astype(np.uint8)
    return {
        "order": order,
        "chunks": chunk_data,
        "packed": packed.astype("<u4"),
        "sh_rest": rest_bytes,
    }


def write_compressed_ply(
    path: str | Path,
    means: np.ndarray,
    quats: np.ndarray,
    log_scales: np.ndarray,
    opacity_logits: np.ndarray,
    sh: np.ndarray,
) -> None:
    """means (G, 3), quats (G, 4) wxyz, log_scales (G, 3), opacity_logits (G,), sh (G, K, 3)
    with K in {1, 4, 9, 16} -> `path` as a compressed PLY (SH bands 1..degree kept)."""
    G, K = sh.shape[:2]
    c = compress_splats(means, quats, log_scales, opacity_logits, sh)
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment written by recon (PlayCanvas compressed splat PLY)",
        f"element chunk {len(c['chunks'])}",
        *(f"property float {p}" for p in CHUNK_PROPS),
        f"element vertex {G}",
        *(f"property uint {p}" for p in VERTEX_PROPS),
    ]
    if K > 1:
        header += [f"element sh {G}", *(f"property uchar f_rest_{i}" for i in range(3 * (K - 1)))]
    with open(path, "wb") as f:
        f.write(("\n".join([*header, "end_header"]) + "\n").encode("ascii"))
        f.write(c["chunks"].tobytes())
        f.write(c["packed"].tobytes())
        f.write(c["sh_rest"].tobytes())


def _ply_elements(f) -> list[tuple[str, int, list[tuple[str, str]]]]:
    if f.readline().strip() != b"ply":
        raise ValueError("not a PLY file")
    elements = []
    while True:
        line = f.readline()
        if not line:
            raise ValueError("PLY header has no end_header")
        words = line.decode("ascii").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and words[1] != "binary_little_endian":
            raise ValueError(f"PLY format {words[1]}: expected binary_little_endian")
        if words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            elements[-1][2].append((words[-1], words[1]))
        elif words[0] == "end_header":
            return elements


def read_compressed_ply(path: str | Path) -> dict[str, np.ndarray]:
    """A compressed PLY -> means, quats (wxyz), log_scales, opacity_logits, sh (G, K, 3),
    decoded as PlayCanvas decodes it (in the file's Morton order)."""
    types = {"float": "<f4", "uint": "<u4", "uchar": "u1"}
    with open(path, "rb") as f:
        elements = _ply_elements(f)
        data = {}
        for name, count, props in elements:
            dtype = np.dtype([(p, types[t]) for p, t in props])
            data[name] = np.frombuffer(f.read(count * dtype.itemsize), dtype=dtype, count=count)
    if "chunk" not in data or "vertex" not in data:
        raise ValueError(f"{path}: not a compressed splat PLY (no chunk / vertex elements)")
    chunk = np.stack([data["chunk"][p] for p in CHUNK_PROPS], 1).astype(np.float64)
    v = data["vertex"]
    G = len(v)
    which = np.arange(G) // CHUNK

    def lerp(t, lo, hi):
        return chunk[which, lo : lo + 3] * (1 - t) + chunk[which, hi : hi + 3] * t

    colour = v["packed_color"]
    rgba = np.stack([(colour >> s) & 0xFF for s in (24, 16, 8, 0)], -1) / 255.0
    rgb = lerp(rgba[:, :3], 12, 15)
    sh = [(rgb - 0.5) / SH_C0]
    if "sh" in data:
        rest = np.stack([data["sh"][n] for n in data["sh"].dtype.names], 1) * (8 / 255) - 4
        coeffs = rest.shape[1] // 3
        sh += list(np.transpose(rest.reshape(G, 3, coeffs), (2, 0, 1)))
    return {
        "means": lerp(_unpack_111011(v["packed_position"]), 0, 3).astype(np.float32),
        "quats": unpack_rotation(v["packed_rotation"]).astype(np.float32),
        "log_scales": lerp(_unpack_111011(v["packed_scale"]), 6, 9).astype(np.float32),
        "opacity_logits": logit(rgba[:, 3]).astype(np.float32),
        "sh": np.stack(sh, 1).astype(np.float32),
    }
