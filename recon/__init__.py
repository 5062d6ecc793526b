"""recon: photos -> camera poses -> trained scene -> renders, meshes and an honest evaluation."""

# zlib must be imported before pycolmap: importing pycolmap first corrupts the heap of the
# zlib users that come later (PNG writes, gzip, numba). Every entry point imports `recon`
# first, so this line protects the whole process.
import os
import zlib  # noqa: F401

# OpenMP threads that spin-wait between parallel regions turn every torch op 3-10x slower as
# soon as anything else shares the cores (measured on 2-core machines); sleep instead. Must be
# set before torch is imported; an explicit setting in the environment wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# oneDNN (the bf16 matmuls of nerf's MLPs) caches one compiled primitive, with its buffers
# (~5 MB here), per matmul shape, up to 1024 of them. A shape that changes every step grew a nerf
# run to 5.9 GB of RSS; nerf now pads its rays to buckets (few shapes), and 128 entries bound the
# rest (lego-200: 159 ms/step and 1.3 GB peak, against 150 ms and 1.7 GB at 1024 and 179 ms and
# 1.2 GB at 16). Read when torch first uses oneDNN; an explicit setting in the environment wins.
os.environ.setdefault("ONEDNN_PRIMITIVE_CACHE_CAPACITY", "128")

__version__ = "0.1.0"
