"""EXR depth and multi-channel I/O: exact float32 round trips, the 0 = no-surface convention,
atomic writes."""

import numpy as np
import OpenEXR
import pytest

from recon.io.exr import (
    depth_valid_mask,
    read_depth_exr,
    read_exr_channels,
    write_depth_exr,
    write_exr_channels,
)


def _depth_with_specials(h=13, w=17):
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.1, 50.0, (h, w)).astype(np.float32)
    depth[0, :] = 0.0  # no surface
    depth[1, 0], depth[1, 1], depth[1, 2] = np.inf, np.nan, -np.inf
    depth[2, 0] = np.finfo(np.float32).tiny  # smallest normal: no flush to zero
    depth[2, 1] = np.float32(1e-42)  # a denormal
    return depth


def test_depth_round_trip_is_bit_exact(tmp_path):
    depth = _depth_with_specials()
    path = tmp_path / "d.exr"
    write_depth_exr(path, depth)
    back = read_depth_exr(path)
    assert back.dtype == np.float32 and back.shape == depth.shape
    assert np.array_equal(back.view(np.uint32), depth.view(np.uint32))


def test_depth_file_is_one_float32_channel_named_z(tmp_path):
    path = tmp_path / "d.exr"
    write_depth_exr(path, np.ones((4, 6)))  # float64 input is stored as float32
    with OpenEXR.File(str(path), separate_channels=True) as f:
        channels = f.channels()
        assert list(channels) == ["Z"]
        assert channels["Z"].pixels.dtype == np.float32
        assert channels["Z"].pixels.shape == (4, 6)


def test_multi_channel_round_trip_and_channel_choice(tmp_path):
    rng = np.random.default_rng(1)
    arrays = {name: rng.normal(size=(5, 3)).astype(np.float32) for name in ("R", "G", "B", "depth")}
    path = tmp_path / "m.exr"
    write_exr_channels(path, arrays)
    back = read_exr_channels(path)
    assert sorted(back) == sorted(arrays)
    for name, array in arrays.items():
        assert np.array_equal(back[name], array)
    assert np.array_equal(read_depth_exr(path, channel="depth"), arrays["depth"])
    with pytest.raises(KeyError, match="no channel 'Z'"):
        read_depth_exr(path)


def test_single_channel_with_another_name_is_read_as_depth(tmp_path):
    path = tmp_path / "y.exr"
    depth = np.arange(12, dtype=np.float32).reshape(3, 4)
    write_depth_exr(path, depth, channel="Y")
    assert np.array_equal(read_depth_exr(path), depth)


def test_bad_shapes_are_refused_and_write_nothing(tmp_path):
    with pytest.raises(ValueError):
        write_depth_exr(tmp_path / "a.exr", np.ones((2, 3, 1)))
    with pytest.raises(ValueError):
        write_exr_channels(tmp_path / "b.exr", {"R": np.ones((2, 3)), "G": np.ones((3, 2))})
    with pytest.raises(ValueError):
        write_exr_channels(tmp_path / "c.exr", {})
    assert list(tmp_path.iterdir()) == []


def test_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path, monkeypatch):
    path = tmp_path / "d.exr"
    old = np.full((3, 3), 2.5, np.float32)
    write_depth_exr(path, old)

    def fail(self, filename):
        with open(filename, "wb") as f:
            f.write(b"half a file")
        raise OSError("disk full")

    monkeypatch.setattr(OpenEXR.File, "write", fail)
    with pytest.raises(OSError, match="disk full"):
        write_depth_exr(path, np.zeros((3, 3), np.float32))
    monkeypatch.undo()
    assert [p.name for p in tmp_path.iterdir()] == ["d.exr"]
    assert np.array_equal(read_depth_exr(path), old)


def test_valid_mask_follows_the_zero_means_no_surface_convention():
    depth = _depth_with_specials(3, 4)
    mask = depth_valid_mask(depth)
    expected = np.isfinite(depth) & (depth > 0)
    assert np.array_equal(mask, expected)
    assert not mask[0].any() and not mask[1, :3].any() and mask[2, 0] and mask[2, 1]
