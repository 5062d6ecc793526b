""".splat and compressed PLY: worked examples of each packed field, the smallest-three
rotation round trip, and renders of the files read back against renders of the Gaussians
written (the viewers' decoding, our renderer)."""

import numpy as np
import pytest
import torch

from recon.gaussians.render import composite_rgb, project_splats
from recon.gaussians.splat_formats import (
    SH_C0,
    morton_order,
    pack_rotation,
    read_compressed_ply,
    read_dot_splat,
    unpack_rotation,
    write_compressed_ply,
    write_dot_splat,
)
from recon.metrics.image import psnr
from tests.models.test_splatting import ring


def cloud(G=3000, K=16, seed=0):
    """G Gaussians in a ball of radius 0.6: small, mostly opaque, random colours and SH."""
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=(G, 3))
    means = (
        direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.random((G, 1)) ** (1 / 3)
    )
    sh = np.zeros((G, K, 3))
    sh[:, 0] = (rng.random((G, 3)) - 0.5) / SH_C0
    sh[:, 1:] = 0.1 * rng.normal(size=(G, K - 1, 3))
    return {
        "means": (0.6 * means).astype(np.float32),
        "quats": rng.normal(size=(G, 4)).astype(np.float32),
        "log_scales": np.log(rng.uniform(0.005, 0.04, size=(G, 3))).astype(np.float32),
        "opacity_logits": rng.normal(2.0, 1.5, size=G).astype(np.float32),
        "sh": sh.astype(np.float32),
    }


def render(g, degree):
    """Mean RGB image of 4 ring views at 96 px, SH up to `degree`."""
    t = {k: torch.from_numpy(np.ascontiguousarray(v)).float() for k, v in g.items()}
    K = (degree + 1) ** 2
    splats = {
        "means": t["means"],
        "quats": t["quats"],
        "log_scales": t["log_scales"],
        "opacity_logits": t["opacity_logits"],
        "sh_dc": t["sh"][:, :1],
        "sh_rest": t["sh"][:, 1:K],
    }
    cams = ring(n=4, size=96, radius=2.5)
    with torch.no_grad():
        return torch.stack(
            [
                composite_rgb(project_splats(splats, cams[i], degree), torch.zeros(3))[0]
                for i in range(4)
            ]
        ).clamp(0, 1)


def write(writer, path, g, K=None):
    sh = g["sh"] if K is None else g["sh"][:, :K]
    writer(path, g["means"], g["quats"], g["log_scales"], g["opacity_logits"], sh)


def test_rotation_worked_examples_and_round_trip():
    # identity: largest is w (index 0); x, y, z = 0 -> 0.5 -> 512 of 1023
    assert (
        pack_rotation(np.array([[1.0, 0, 0, 0]]))[0] == (0 << 30) | (512 << 20) | (512 << 10) | 512
    )
    # -z (w, x, y, z) = (0, 0, 0, -1): largest index 3, sign flipped to +1, others 0
    bits = pack_rotation(np.array([[0.0, 0, 0, -1]]))[0]
    assert bits >> 30 == 3 and np.allclose(
        unpack_rotation(np.array([bits]))[0], [0, 0, 0, 1], atol=2e-3
    )
    rng = np.random.default_rng(1)
    q = rng.normal(size=(5000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    back = unpack_rotation(pack_rotation(q))
    same_rotation = np.abs((back * q).sum(1))  # q and -q are the same rotation
    assert same_rotation.min() > 1 - 2e-6 and np.allclose(
        np.linalg.norm(back, axis=1), 1, atol=1e-3
    )


def test_dot_splat_worked_example(tmp_path):
    """One Gaussian: position and exp(scales) as float32, colour 255 (0.5 + C0 f_dc), alpha
    255 sigmoid(opacity), quaternion 128 q + 128 of the unit (w, x, y, z)."""
    path = tmp_path / "one.splat"
    dc = np.array([[0.0, 1.0, -1.0]]) / SH_C0 * 0.5  # colour (0.5, 1.0, 0.0)
    write_dot_splat(
        path,
        np.array([[1.0, -2.0, 3.0]]),
        np.array([[2.0, 0.0, 0.0, 0.0]]),  # not unit: normalised first
        np.log(np.array([[0.5, 1.0, 2.0]])),
        np.array([0.0]),  # alpha 0.5
        dc,
    )
    raw = path.read_bytes()
    assert len(raw) == 32
    assert np.frombuffer(raw[:24], "<f4").tolist() == [1.0, -2.0, 3.0, 0.5, 1.0, 2.0]
    assert list(raw[24:]) == [128, 255, 0, 128, 255, 128, 128, 128]  # rint(127.5) = 128
    back = read_dot_splat(path)
    assert np.allclose(back["quats"], [[1, 0, 0, 0]], atol=1e-2)
    assert np.allclose(back["log_scales"], np.log([[0.5, 1.0, 2.0]]), atol=1e-6)
    with pytest.raises(ValueError, match="32-byte"):
        (tmp_path / "bad.splat").write_bytes(raw + b"x")
        read_dot_splat(tmp_path / "bad.splat")


def test_compressed_ply_layout_and_fields(tmp_path):
    g = cloud(G=600, K=4)
    path = tmp_path / "scene.compressed.ply"
    write(write_compressed_ply, path, g)
    raw = path.read_bytes()
    header = raw[: raw.index(b"end_header\n") + 11].decode()
    assert "element chunk 3\n" in header and "element vertex 600\n" in header
    assert "element sh 600\n" in header and "property uchar f_rest_8\n" in header
    assert "f_rest_9" not in header  # degree 1: 3 coefficients x 3 channels
    assert len(raw) - len(header) == 3 * 18 * 4 + 600 * 16 + 600 * 9
    back = read_compressed_ply(path)
    order = morton_order(g["means"].astype(np.float64))
    extent = g["means"].max(0) - g["means"].min(0)
    # positions: 11-10-11 bits of a chunk's box, far finer than the cloud
    assert np.abs(back["means"] - g["means"][order]).max() < extent.max() / 200
    alpha = 1 / (1 + np.exp(-g["opacity_logits"][order]))
    assert np.abs(1 / (1 + np.exp(-back["opacity_logits"])) - alpha).max() <= 0.5 / 255 + 1e-6
    assert np.abs(back["sh"][:, 1:] - g["sh"][order, 1:]).max() <= 8 / 256 + 1e-6
    assert np.abs(back["log_scales"] - g["log_scales"][order]).max() < 0.01


@pytest.mark.parametrize("degree", [3, 1, 0])
def test_compressed_ply_renders_like_the_gaussians(tmp_path, degree):
    g = cloud()
    K = (degree + 1) ** 2
    path = tmp_path / "scene.compressed.ply"
    write(write_compressed_ply, path, g, K)
    back = read_compressed_ply(path)
    assert back["sh"].shape[1] == K
    quality = float(psnr(render(back, degree), render(g, degree)).min())
    assert quality > 45.0, quality


def test_dot_splat_renders_like_the_base_colours(tmp_path):
    g = cloud()
    path = tmp_path / "scene.splat"
    write_dot_splat(
        path, g["means"], g["quats"], g["log_scales"], g["opacity_logits"], g["sh"][:, 0]
    )
    back = read_dot_splat(path)
    assert path.stat().st_size == 32 * len(g["means"])
    quality = float(psnr(render(back, 0), render(g, 0)).min())
    assert quality > 55.0, quality  # float positions and scales: only colour bytes
    # the view-dependent colour is gone: against the full degree-3 render it is worse
    assert float(psnr(render(back, 0), render(g, 3)).min()) < quality - 3


def test_morton_order_keeps_chunks_small():
    rng = np.random.default_rng(0)
    points = rng.random((256 * 64, 3))
    chunks = points[morton_order(points)].reshape(64, 256, 3)
    spans = chunks.max(1) - chunks.min(1)
    assert np.prod(spans, axis=1).mean() < 4 / 64  # a random split: ~1 (the whole cube)
