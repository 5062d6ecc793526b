"""Stage 5, `recon eval`: image, geometry, pose and speed metrics per run, and one report
comparing every run of the workspace (seed, "The evaluation-metric trap": PSNR and geometry
side by side)."""
