"""INRIA splat PLY: header layout, channel-major f_rest, round trip, degree < 3 padding."""

import numpy as np
import pytest

from recon.gaussians.ply import read_splat_ply, splat_dtype, write_splat_ply


def random_splats(G, K, seed=0):
    rng = np.random.default_rng(seed)
    return {
        "means": rng.normal(size=(G, 3)).astype(np.float32),
        "quats": rng.normal(size=(G, 4)).astype(np.float32),
        "log_scales": rng.normal(size=(G, 3)).astype(np.float32),
        "opacity_logits": rng.normal(size=G).astype(np.float32),
        "sh": rng.normal(size=(G, K, 3)).astype(np.float32),
    }


def test_round_trip_degree_3(tmp_path):
    s = random_splats(7, 16)
    path = tmp_path / "splat.ply"
    write_splat_ply(path, s["means"], s["quats"], s["log_scales"], s["opacity_logits"], s["sh"])
    back = read_splat_ply(path)
    for key in s:
        assert np.array_equal(back[key], s[key]), key


def test_header_is_the_inria_layout(tmp_path):
    s = random_splats(3, 16)
    path = tmp_path / "splat.ply"
    write_splat_ply(path, s["means"], s["quats"], s["log_scales"], s["opacity_logits"], s["sh"])
    raw = path.read_bytes()
    header = raw[: raw.index(b"end_header\n") + len(b"end_header\n")].decode()
    props = [line.split()[-1] for line in header.splitlines() if line.startswith("property float")]
    assert header.startswith("ply\nformat binary_little_endian 1.0\nelement vertex 3\n")
    assert props[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert props[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert props[54:] == [
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
    ]
    assert len(raw) - len(header) == 3 * 62 * 4  # 62 float32 per Gaussian
    vertices = np.frombuffer(raw[len(header) :], dtype=splat_dtype())
    # Channel-major: f_rest_0..14 are the red coefficients 1..15, f_rest_15 the first green one.
    assert vertices["f_rest_0"][1] == s["sh"][1, 1, 0]
    assert vertices["f_rest_14"][1] == s["sh"][1, 15, 0]
    assert vertices["f_rest_15"][1] == s["sh"][1, 1, 1]
    assert vertices["f_rest_44"][2] == s["sh"][2, 15, 2]
    assert vertices["rot_0"][0] == s["quats"][0, 0]  # w first


def test_degree_1_is_padded_with_zeros(tmp_path):
    s = random_splats(5, 4)
    path = tmp_path / "splat.ply"
    write_splat_ply(path, s["means"], s["quats"], s["log_scales"], s["opacity_logits"], s["sh"])
    back = read_splat_ply(path)
    assert back["sh"].shape == (5, 16, 3)
    assert np.array_equal(back["sh"][:, :4], s["sh"]) and not back["sh"][:, 4:].any()


def test_reader_accepts_fewer_f_rest_and_rejects_ascii(tmp_path):
    names = (
        ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(9)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    values = np.arange(2 * len(names), dtype="<f4").reshape(2, -1)
    header = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 2\n"
        + "".join(f"property float {n}\n" for n in names)
        + "end_header\n"
    )
    path = tmp_path / "deg1.ply"
    path.write_bytes(header.encode() + values.tobytes())
    back = read_splat_ply(path)
    rest = values[:, 6:15].reshape(2, 3, 3)  # channel-major, 3 coefficients each
    assert np.array_equal(back["sh"][:, 1:4], rest.transpose(0, 2, 1))
    assert np.array_equal(back["means"], values[:, :3])
    ascii_path = tmp_path / "ascii.ply"
    ascii_path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(ValueError, match="little-endian"):
        read_splat_ply(ascii_path)
