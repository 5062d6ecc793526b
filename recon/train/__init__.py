"""Stage 2, `recon train`: fit a representation to the sfm scene, with logging, atomic
checkpoints, resume, time budgets and convergence-based stopping."""
