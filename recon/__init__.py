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

# oneDNN (the bf16 matmuls of nerf's MLPs) caches one compiled primitive, with its buffers, per
# matmul shape, up to 1024 of them. Occupancy skipping makes the row count differ every step, so
# the default cache grew a nerf run to 5.9 GB of RSS (4.2 GB after 250 steps); 16 entries keep it
# ~1.5 GB at the same step time (measured on lego-200). Read when torch first uses oneDNN.
os.environ.setdefault("ONEDNN_PRIMITIVE_CACHE_CAPACITY", "16")

__version__ = "0.1.0"
