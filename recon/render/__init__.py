"""Stage 3, `recon render`: images, metric depth and videos from a trained run."""
