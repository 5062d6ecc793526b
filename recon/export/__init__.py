"""`recon export`: trained scenes in formats other tools read (the INRIA splat PLY)."""
