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

__version__ = "0.1.0"
