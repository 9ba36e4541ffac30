"""Evaluation of a fitted run, one module per kind of score: ``loaders`` (the run's predictions, masks, keypoints,
ground truth), ``image`` (mask IoU, PCK-T), ``shape`` (alignment, Chamfer, F-score), ``skeleton`` (joint distance,
limb coverage and identity, joints inside, empty bones) and ``report`` (``evaluate_run``, ``metrics.json``, the
table)."""
