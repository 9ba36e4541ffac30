"""Evaluation: mask IoU, PCK-T, 3D shape and skeleton metrics."""
