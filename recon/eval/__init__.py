"""Stage 5, `recon eval`: image, geometry, pose and speed metrics per run, and one report
comparing every run of the workspace (PSNR says little about geometry,
so both are reported side by side)."""
