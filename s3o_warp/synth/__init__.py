"""Synthetic sequences with ground truth: a procedural quadruped or a skinned glTF, rendered in the
input contract (see :mod:`s3o_warp.synth.sequence` for the folder format)."""
