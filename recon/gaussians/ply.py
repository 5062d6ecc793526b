"""The de-facto INRIA splat PLY (what common splat viewers load): binary little-endian, one
float32 vertex per Gaussian with properties
    x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2 rot_0..3
where f_rest is channel-major (all R coefficients of degrees 1-3, then G, then B), opacity is
the logit, scales are logs and rot is the (w, x, y, z) quaternion, unnormalised. Models of
degree < 3 are written with zero-padded f_rest, as viewers expect 45 of them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

REST_COEFFS = 15  # SH coefficients of degrees 1..3 per channel


def splat_dtype() -> np.dtype:
    names = (
        ["x", "y", "z", "nx", "ny", "nz"]
        + [f"f_dc_{i}" for i in range(3)]
        + [f"f_rest_{i}" for i in range(3 * REST_COEFFS)]
        + ["opacity"]
        + [f"scale_{i}" for i in range(3)]
        + [f"rot_{i}" for i in range(4)]
    )
    return np.dtype([(n, "<f4") for n in names])


def write_splat_ply(
    path: str | Path,
    means: np.ndarray,
    quats: np.ndarray,
    log_scales: np.ndarray,
    opacity_logits: np.ndarray,
    sh: np.ndarray,
) -> None:
    """means (G, 3), quats (G, 4) wxyz, log_scales (G, 3), opacity_logits (G,), sh (G, K, 3)
    with K = (degree + 1)^2 <= 16 -> a binary splat PLY at `path`."""
    G, K = sh.shape[0], sh.shape[1]
    if K > REST_COEFFS + 1:
        raise ValueError(f"SH with {K} coefficients per channel; the splat PLY holds at most 16")
    rest = np.zeros((G, 3, REST_COEFFS), np.float32)
    rest[:, :, : K - 1] = np.transpose(sh[:, 1:], (0, 2, 1))  # (G, K-1, 3) -> channel-major
    columns = np.concatenate(
        [
            means,
            np.zeros((G, 3)),
            sh[:, 0],
            rest.reshape(G, -1),
            opacity_logits.reshape(G, 1),
            log_scales,
            quats,
        ],
        axis=1,
    ).astype("<f4")
    vertices = np.empty(G, dtype=splat_dtype())
    vertices.view("<f4").reshape(G, -1)[:] = columns
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {G}\n"
        + "".join(f"property float {n}\n" for n in splat_dtype().names)
        + "end_header\n"
    )
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(vertices.tobytes())


def _read_header(f) -> tuple[int, list[str]]:
    """-> vertex count and vertex property names; the vertex element must come first."""
    if f.readline().strip() != b"ply":
        raise ValueError("not a PLY file")
    count, names, element = None, [], None
    while (line := f.readline()) and line.strip() != b"end_header":
        words = line.decode("ascii").split()
        if words[:1] == ["format"] and words[1] != "binary_little_endian":
            raise ValueError(f"only binary little-endian splat PLYs are supported, got {words[1]}")
        if words[:1] == ["element"]:
            element = words[1]
            if element == "vertex":
                count = int(words[2])
            elif count is None:
                raise ValueError(f"PLY element {element!r} comes before the vertices")
        elif words[:1] == ["property"] and element == "vertex":
            if words[1] not in ("float", "float32"):
                raise ValueError(f"property {words[-1]} is {words[1]}; splat PLYs use float")
            names.append(words[-1])
    if count is None:
        raise ValueError("PLY has no vertex element")
    return count, names


def read_splat_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Inverse of `write_splat_ply` -> means, quats, log_scales, opacity_logits, sh (G, 16, 3).

    Any number of f_rest_* (3 (K - 1)) is accepted; missing coefficients are zero."""
    with open(path, "rb") as f:
        count, names = _read_header(f)
        data = np.frombuffer(f.read(4 * count * len(names)), dtype="<f4").reshape(count, -1)
    col = {n: data[:, i] for i, n in enumerate(names)}

    def stack(keys):
        return np.stack([col[k] for k in keys], axis=1).astype(np.float32)

    n_rest = sum(n.startswith("f_rest_") for n in names) // 3
    sh = np.zeros((count, REST_COEFFS + 1, 3), np.float32)
    sh[:, 0] = stack([f"f_dc_{i}" for i in range(3)])
    rest = stack([f"f_rest_{i}" for i in range(3 * n_rest)]).reshape(count, 3, n_rest)
    sh[:, 1 : 1 + n_rest] = np.transpose(rest, (0, 2, 1))
    return {
        "means": stack("xyz"),
        "quats": stack([f"rot_{i}" for i in range(4)]),
        "log_scales": stack([f"scale_{i}" for i in range(3)]),
        "opacity_logits": col["opacity"].astype(np.float32),
        "sh": sh,
    }
