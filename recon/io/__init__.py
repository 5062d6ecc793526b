"""File formats at the edge of the pipeline: images, PLY point clouds, EXR depth."""
