"""Evaluation metrics: image (PSNR, SSIM, depth errors), perceptual (LPIPS) and geometry
(accuracy, completeness, Chamfer, F-score, normal consistency). Pure functions of arrays."""
