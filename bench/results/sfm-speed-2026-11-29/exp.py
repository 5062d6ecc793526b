import sys, time, json, shutil
from pathlib import Path
from dataclasses import replace
import numpy as np
sys.path.insert(0, "/work/main/pipelines")
import recon
from recon.sfm import colmap_steps as steps, colmap_sfm as S
from recon.sfm.colmap_config import SfmConfig
from recon.sfm.photos import prepare_photos
import pycolmap
from bench_sfm import reference_poses, estimated_poses, accuracy
fox = Path("/work/shared/data/fox")
size, feats, mode, k = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], int(sys.argv[4])
mapper = sys.argv[5] if len(sys.argv) > 5 else "incremental"
work = Path(f"/tmp/sfmx/w_{size}_{feats}")
cfg = replace(SfmConfig(), max_image_size=size, max_num_features=feats)
opts = S.attempt_ladder(cfg, 67)[0]
nop = lambda *a: None
import os
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
  photos = prepare_photos(fox / "images", work / "images")
  db = work / "database.db"
  groups = S.camera_groups(photos, True)
  t0 = time.perf_counter()
  if not db.exists():
    steps.extract_features(db, photos.staging_dir, groups, opts, "OPENCV", -1, nop)
  t["features"] = time.perf_counter() - t0
  run = work / f"run_{mode}_{k}"; shutil.rmtree(run, ignore_errors=True); run.mkdir()
  rdb = run / "database.db"
  from recon.sfm.colmap_retry import copy_database
  copy_database(db, rdb)
  t0 = time.perf_counter()
  if mode == "exh":
    pairs = steps.exhaustive_pairs(photos.names)
  elif mode == "seq":
    pairs = steps.sequential_pairs(photos.names, overlap=k)
  else:
    import retrieval
    pairs = retrieval.pairs(rdb, photos.names, k)
  t["select"] = time.perf_counter() - t0
  t0 = time.perf_counter()
  steps.match_pairs(rdb, run, pairs, opts, 0, -1, nop)
  t["matching"] = time.perf_counter() - t0
  t0 = time.perf_counter()
  models = steps.map_images(rdb, photos.staging_dir, run / "sparse", photos.names, mapper, opts, 0, -1, nop)
  t["mapping"] = time.perf_counter() - t0
  best = max(models.values(), key=lambda m: m.num_reg_images())
  t0 = time.perf_counter()
  steps.refine_intrinsics(best, True)
  t["refine"] = time.perf_counter() - t0
acc = accuracy(estimated_poses(best), reference_poses(fox / "transforms.json"))
print(json.dumps({"size": size, "feats": feats, "mode": mode, "k": k, "mapper": mapper, "ovr": os.environ.get("OVR", ""), "pairs": len(pairs), "reg": best.num_reg_images(),
  "rot": acc["median_rotation_error_deg"], "ctr": acc["median_center_error_pct"], "maxrot": acc["max_rotation_error_deg"],
  **{a: round(b, 2) for a, b in t.items()}}))
