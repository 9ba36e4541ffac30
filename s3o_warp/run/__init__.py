"""A run directory: checkpoints, branches, outputs and pictures."""
