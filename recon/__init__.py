"""recon: photos -> camera poses -> trained scene -> renders, meshes and an honest evaluation."""

# zlib must be imported before pycolmap: importing pycolmap first corrupts the heap of the
# zlib users that come later (PNG writes, gzip, numba). Every entry point imports `recon`
# first, so this line protects the whole process.
import zlib  # noqa: F401

__version__ = "0.1.0"
