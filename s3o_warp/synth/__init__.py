"""Synthetic sequences with ground truth: a procedural quadruped or lizard, or a skinned glTF model, rendered
with the project's rasteriser into the input contract (folder format: :mod:`s3o_warp.synth.sequence`).

Public API:
    make_sequence(out_dir, source="quadruped" | "lizard" | path.glb, clip=None, frames=48, fps=24, size=(W, H), ...)
    build_quadruped(frames, fps, seed, ...) -> AnimatedMesh
    build_lizard(frames, fps, seed, ...) -> AnimatedMesh
    load_gltf(path, clip=None, fps=30, frames=None) -> AnimatedMesh
"""

from .camera import camera_path, intrinsics, look_at
from .gltf import clip_names, gltf_keypoints, load_gltf
from .lizard import build_lizard, lizard_keypoints
from .model import AnimatedMesh, vertex_normals
from .quadruped import build_quadruped, keypoint_vertices
from .sequence import Shot, keypoint_visibility, make_sequence

__all__ = [
    "AnimatedMesh", "Shot", "build_lizard", "build_quadruped", "camera_path", "clip_names", "gltf_keypoints",
    "intrinsics", "keypoint_vertices", "keypoint_visibility", "lizard_keypoints", "load_gltf", "look_at", "make_sequence",
    "vertex_normals",
]
