"""recon's own COLMAP binary writer against COLMAP's reader (pycolmap, in a subprocess: pycolmap
imported next to zlib users in one process can corrupt the heap)."""

import json
import subprocess
import sys

import numpy as np
from scipy.spatial.transform import Rotation

from recon.io.colmap_binary import quat_wxyz, write_colmap_binary

READ = """
import json, sys
import numpy as np
import pycolmap
rec = pycolmap.Reconstruction(sys.argv[1])
out = {"cameras": {}, "images": {}, "points": []}
for cid, cam in rec.cameras.items():
    out["cameras"][cid] = [cam.model.name, cam.width, cam.height, list(cam.params)]
for iid, im in rec.images.items():
    m = im.cam_from_world().matrix()
    out["images"][iid] = [im.name, im.camera_id, np.asarray(m).tolist()]
for pid, p in rec.points3D.items():
    out["points"].append([list(p.xyz), [int(c) for c in p.color]])
print(json.dumps(out))
"""


def test_quat_worked_example():
    q = quat_wxyz(Rotation.from_euler("z", 90, degrees=True).as_matrix())
    np.testing.assert_allclose(q, [0.5**0.5, 0, 0, 0.5**0.5], atol=1e-12)
    q = quat_wxyz(Rotation.from_euler("x", 270, degrees=True).as_matrix())
    assert q[0] >= 0


def test_pycolmap_reads_what_recon_writes(tmp_path):
    rng = np.random.default_rng(0)
    poses = []
    for _ in range(3):
        m = np.eye(4)
        m[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        m[:3, 3] = rng.normal(size=3)
        poses.append(m)
    cameras = [(1, 640, 480, 500.0, 501.0, 320.5, 240.25), (2, 200, 100, 90.0, 90.0, 99.0, 51.0)]
    images = [(1, "a.png", 1, poses[0]), (2, "sub/b.png", 2, poses[1]), (3, "c.jpg", 1, poses[2])]
    points = rng.normal(size=(5, 3))
    colors = rng.integers(0, 256, size=(5, 3))
    write_colmap_binary(tmp_path, cameras, images, points, colors)
    proc = subprocess.run(
        [sys.executable, "-c", READ, str(tmp_path)], capture_output=True, text=True, check=True
    )
    read = json.loads(proc.stdout)
    assert read["cameras"]["1"] == ["PINHOLE", 640, 480, [500.0, 501.0, 320.5, 240.25]]
    assert read["cameras"]["2"][1:3] == [200, 100]
    for image_id, name, cam_id, pose in images:
        got_name, got_cam, got_pose = read["images"][str(image_id)]
        assert (got_name, got_cam) == (name, cam_id)
        np.testing.assert_allclose(got_pose, pose[:3], atol=1e-12)
    got = sorted(read["points"])
    want = sorted([list(p), list(c)] for p, c in zip(points.tolist(), colors.tolist()))
    for (gp, gc), (wp, wc) in zip(got, want):
        np.testing.assert_allclose(gp, wp, atol=1e-12)
        assert gc == wc
