"""Stage 1, `recon sfm`: camera poses and sparse points, from photos (COLMAP via pycolmap) or
from known poses (transforms.json, a COLMAP model), written as one normalized scene."""
