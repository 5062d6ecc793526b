"""Evaluation metrics: image (PSNR, SSIM, depth errors), perceptual (LPIPS) and geometry
(accuracy, completeness, Chamfer, F-score, normal consistency). Pure functions of arrays."""

from recon.metrics.geometry import geometry_metrics, point_cloud_metrics
from recon.metrics.image import depth_errors, psnr, ssim

# `recon.metrics.lpips` stays the module (its distance function is `lpips.lpips`).
from recon.metrics.lpips import load_lpips

__all__ = [
    "depth_errors",
    "geometry_metrics",
    "load_lpips",
    "point_cloud_metrics",
    "psnr",
    "ssim",
]
