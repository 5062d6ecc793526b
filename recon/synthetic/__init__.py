"""Synthetic ground truth: a procedural textured scene and the exact rasterizer that renders it."""
