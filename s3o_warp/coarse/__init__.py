"""Phase 1 (paper 3.2): skeleton2d.py (the canonical frame's 2D skeleton), lift.py (ellipsoids, their union mesh
and Gaussian bones) and model.py (the coarse model and the coarse fit's objective)."""
