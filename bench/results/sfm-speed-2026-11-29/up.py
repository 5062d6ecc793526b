import sys
sys.path.insert(0, "/work/main/pipelines")
import recon
from recon.sfm import colmap_steps
colmap_steps.SIFT_UPSAMPLE_BELOW = int(sys.argv.pop(1))
import bench_sfm
bench_sfm.main()
