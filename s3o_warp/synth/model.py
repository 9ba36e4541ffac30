"""The animated, skinned mesh that every synthetic source returns (procedural quadruped or glTF).

Object frame: +y up, right-handed. The procedural quadruped faces +x (so +z is its right side);
glTF models keep their own frame (the glTF spec's +y up, +z front) and their own units (metres).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import sparse


@dataclass
class AnimatedMesh:
    """A skinned mesh sampled at a fixed frame rate, with its skeleton.

    Attributes:
        rest_verts: float32 (V, 3), the mesh in its rest pose, object frame.
        faces: int32 (F, 3), triangle vertex indices, counter-clockwise seen from outside.
        verts: float32 (T, V, 3), skinned vertices per frame, object (world) frame.
        joint_names: J names.
        parents: int32 (J,), parent joint index, -1 for a root; parents precede children.
        joints: float32 (T, J, 3), joint world positions per frame (the joint's origin).
        deforming: bool (J,), True for joints that move the skin (a non-zero skin weight on some
            vertex) or, for the procedural model, every joint of the physical skeleton.
        weights: float32 (V, J), skinning weights, rows sum to 1.
        rest_joints: float32 (J, 3), joint positions in the rest pose (the pose of ``rest_verts``).
        fps: frames per second of ``verts``/``joints``.
        clip_names: animation clips in the source (the sampled one is ``clip``).
        clip: name of the sampled clip ("" when the source has none).
        colors: float32 (V, 3) sRGB base colour in [0, 1] per vertex, or None.
        source: a short description of where the model came from.
    """

    rest_verts: np.ndarray
    faces: np.ndarray
    verts: np.ndarray
    joint_names: list[str]
    parents: np.ndarray
    joints: np.ndarray
    deforming: np.ndarray
    weights: np.ndarray
    rest_joints: np.ndarray
    fps: float
    clip_names: list[str] = field(default_factory=list)
    clip: str = ""
    colors: np.ndarray | None = None
    source: str = ""

    @property
    def num_frames(self) -> int:
        """T, the number of sampled frames."""
        return int(self.verts.shape[0])


def vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals.

    Args:
        verts: float (V, 3) or (T, V, 3) vertices.
        faces: int (F, 3).

    Returns:
        float32, same shape as ``verts``, unit normals (isolated vertices get zero vectors).
    """
    v = np.asarray(verts, dtype=np.float64)
    batched = v.ndim == 3
    if not batched:
        v = v[None]
    num_v, num_f = v.shape[1], faces.shape[0]
    a, b, c = v[:, faces[:, 0]], v[:, faces[:, 1]], v[:, faces[:, 2]]
    fn = np.cross(b - a, c - a)  # (T, F, 3), length = 2 * area
    rows = faces.reshape(-1)
    cols = np.repeat(np.arange(num_f), 3)
    incidence = sparse.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(num_v, num_f))
    n = np.stack([incidence @ fn[t] for t in range(v.shape[0])])
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    n = n.astype(np.float32)
    return n if batched else n[0]
