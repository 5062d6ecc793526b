import sys, time, json, os
from pathlib import Path
from dataclasses import replace
sys.path.insert(0, "/work/main/pipelines")
import recon
from recon.sfm import colmap_steps as steps, colmap_sfm as S
from recon.sfm.colmap_config import SfmConfig
from recon.sfm.colmap_retry import copy_database
from bench_sfm import reference_poses, estimated_poses, accuracy
src_db, images, transforms, mapper = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]), sys.argv[4]
run = Path("/tmp/sfmx/maprun"); import shutil; shutil.rmtree(run, ignore_errors=True); run.mkdir()
copy_database(src_db, run / "database.db")
names = sorted(p.name for p in images.iterdir())
opts = S.attempt_ladder(SfmConfig(), len(names))[0]
_io = steps.incremental_options
def _patched(*a, **kw):
    p = _io(*a, **kw)
    for key, val in json.loads(os.environ.get("OVR", "{}")).items():
        obj = p
        *path, last = key.split(".")
        for q in path: obj = getattr(obj, q)
        setattr(obj, last, val)
    return p
steps.incremental_options = _patched
t = {}
with steps.glog_level(False):
    t0 = time.perf_counter(); c0 = time.process_time()
    models = steps.map_images(run / "database.db", images, run / "sparse", names, mapper, opts, 0, -1, lambda *a: None)
    t["mapping"] = (round(time.perf_counter() - t0, 1), round(time.process_time() - c0, 1))
    best = max(models.values(), key=lambda m: m.num_reg_images())
    t0 = time.perf_counter(); c0 = time.process_time()
    steps.refine_intrinsics(best, True)
    t["refine"] = (round(time.perf_counter() - t0, 1), round(time.process_time() - c0, 1))
acc = accuracy(estimated_poses(best), reference_poses(transforms))
print(json.dumps({"mapper": mapper, "ovr": os.environ.get("OVR", ""), "reg": best.num_reg_images(), "points": best.num_points3D(),
  "rot": acc["median_rotation_error_deg"], "ctr": acc["median_center_error_pct"], "maxrot": acc["max_rotation_error_deg"], **t}))
