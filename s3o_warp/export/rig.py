"""The rig contract that every exporter reads, and its run-directory files.

A :class:`Rig` is everything a DCC tool needs to replay a fit: the canonical mesh in the OBJECT
frame, linear-blend skinning weights, the learned kinematic tree with each bone's rest frame, one
rigid transform per bone and frame, the object-to-camera root pose and the intrinsics of every
frame. Its :meth:`Rig.posed_object`, :meth:`Rig.posed_camera` and :meth:`Rig.project` (numpy
float64) are "the project's posed vertices" that the exported USD and glTF files must reproduce.

Frames used here:

- OBJECT frame: where the canonical mesh lives (OpenCV-like: y down).
- OpenCV camera frame of frame t: ``root[t] @ X_object`` (+x right, +y down, +z forward).
- WORLD frame of the exported files (Y up): ``world_from_object @ X_object``. The animated skeleton
  carries the articulation (world transform of bone b at t: ``world_from_object @ A_b(t) @ bind_b``)
  and the animated camera carries the root motion:
  ``camera_to_world(t) = world_from_object @ inv(root[t]) @ diag(1, -1, -1, 1)``.

Run-directory files (``save_rig`` / ``load_rig``), each written atomically (:mod:`s3o_warp.data.io`):
``canonical.ply`` (mesh with vertex colours), ``skeleton.json`` (bones, joints, tree roots) and
``motion.npz`` (motion, camera, weights and the evaluation keys ``verts_cam``, ``faces``, ``K``,
``image_size``, ``frame_names`` and ``joints_cam`` that the metrics reader expects).
"""

from __future__ import annotations

import json
import logging
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from s3o_warp.data.io import write_bytes, write_stream
from s3o_warp.errors import InputError
from s3o_warp.geometry import project_np

logger = logging.getLogger(__name__)

#: Default world_from_object: a 180 degree turn about x (OpenCV-like y-down object frame -> Y up).
Y_UP_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
#: OpenCV camera axes (+y down, +z forward) -> USD/glTF camera axes (+y up, looking down -z).
CAMERA_GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])

_RIGID_TOL = 1e-3


def _rigid_error(m: np.ndarray) -> float:
    """Largest deviation of a stack of (..., 4, 4) matrices from a proper rigid transform."""
    r = m[..., :3, :3]
    eye = np.eye(3)
    ortho = np.abs(np.swapaxes(r, -1, -2) @ r - eye).max(initial=0.0)
    det = np.abs(np.linalg.det(r) - 1.0).max(initial=0.0) if r.size else 0.0
    last = np.abs(m[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(initial=0.0)
    return float(max(ortho, det, last))


@dataclass
class Rig:
    """A rigged, animated reconstruction: the one input of every exporter.

    Attributes:
        verts: (N, 3) float32, canonical mesh vertices in the OBJECT frame (scene units).
        faces: (F, 3) int32, vertex indices of each triangle (counter-clockwise seen from outside).
        colors: (N, 3) float32 in [0, 1], linear RGB vertex colours.
        weights: (N, B) float32, skinning weights W[n, b]; every row sums to 1.
        bone_names: B readable bone names (``bone_03``); made unique and path-safe on export.
        parents: (B,) int, parent bone of each bone in the learned kinematic tree, -1 for a root.
            Several roots are allowed; exporters put them under one identity ``root`` joint.
        bind: (B, 4, 4) float64, each bone's rigid rest frame in the OBJECT frame
            (rotation = bone orientation, translation = bone centre or joint position).
        bone_motion: (T, B, 4, 4) float64, rigid A_b(t) in the OBJECT frame: posed object-frame
            vertices are X_n(t) = sum_b W[n, b] A_b(t) X_n (linear blend skinning).
        root: (T, 4, 4) float64, rigid object -> OpenCV camera transform of frame t (T_0^t).
        K: (T, 3, 3) float64, full-frame OpenCV intrinsics of frame t (pixel (c, r) centred at (c, r)).
        image_size: (H, W) of the input frames in pixels.
        fps: frames per second of the video.
        frame_names: T names of the input frames (image stems), in time order.
        world_from_object: (4, 4) rigid OBJECT -> exported WORLD (Y up) transform.
        joints: optional (J, 3) object-frame joint positions (for drawing and evaluation).
        joint_pairs: optional (J, 2) int, the two bones each joint connects.
        centres: optional (B, 3) Gaussian bone centres C_b (object frame), for skeleton.json.
        precisions: optional (B, 3, 3) Gaussian bone precisions Q_b, for skeleton.json.
        lengths: optional (B,) bone lengths, for skeleton.json.
    """

    verts: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    weights: np.ndarray
    bone_names: list[str]
    parents: np.ndarray
    bind: np.ndarray
    bone_motion: np.ndarray
    root: np.ndarray
    K: np.ndarray
    image_size: tuple[int, int]
    fps: float
    frame_names: list[str] | None = None
    world_from_object: np.ndarray = field(default_factory=lambda: Y_UP_FROM_OPENCV.copy())
    joints: np.ndarray | None = None
    joint_pairs: np.ndarray | None = None
    centres: np.ndarray | None = None
    precisions: np.ndarray | None = None
    lengths: np.ndarray | None = None

    def __post_init__(self) -> None:
        def arr(name, dtype, shape):
            value = getattr(self, name)
            try:
                a = np.asarray(value, dtype=dtype)
            except (TypeError, ValueError) as exc:
                raise InputError(f"Rig.{name}: cannot be read as {np.dtype(dtype).name} ({exc}); pass an array") from None
            if a.ndim != len(shape) or any(s is not None and a.shape[i] != s for i, s in enumerate(shape)):
                want = "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"
                raise InputError(f"Rig.{name}: must have shape {want}, got {a.shape}; fix the array passed as {name}")
            if np.issubdtype(a.dtype, np.floating) and not np.isfinite(a).all():
                raise InputError(f"Rig.{name}: contains NaN or inf; fix the fit that produced it")
            setattr(self, name, a)
            return a

        v = arr("verts", np.float32, (None, 3))
        n = v.shape[0]
        arr("faces", np.int32, (None, 3))
        arr("colors", np.float32, (n, 3))
        w = arr("weights", np.float32, (n, None))
        b = w.shape[1]
        if n == 0 or b == 0:
            raise InputError(f"Rig: needs at least one vertex and one bone, got N={n}, B={b}")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= n):
            raise InputError(f"Rig.faces: indices must lie in [0, {n}), got [{self.faces.min()}, {self.faces.max()}]")
        if (w < -1e-6).any() or np.abs(w.sum(1) - 1.0).max() > 1e-3:
            raise InputError("Rig.weights: rows must be non-negative and sum to 1 (normalise them, e.g. a softmax over bones)")
        self.bone_names = [str(s) for s in self.bone_names]
        if len(self.bone_names) != b:
            raise InputError(f"Rig.bone_names: need one name per bone ({b}), got {len(self.bone_names)}")
        p = arr("parents", np.int64, (b,))
        if ((p < -1) | (p >= b)).any():
            raise InputError(f"Rig.parents: entries must be -1 (a root) or a bone index in [0, {b})")
        self.topological_order()  # raises on a cycle
        arr("bind", np.float64, (b, 4, 4))
        m = arr("bone_motion", np.float64, (None, b, 4, 4))
        t = m.shape[0]
        if t == 0:
            raise InputError("Rig.bone_motion: needs at least one frame")
        arr("root", np.float64, (t, 4, 4))
        k = arr("K", np.float64, (t, 3, 3))
        arr("world_from_object", np.float64, (4, 4))
        for name in ("bind", "bone_motion", "root", "world_from_object"):
            err = _rigid_error(getattr(self, name))
            if err > _RIGID_TOL:
                raise InputError(
                    f"Rig.{name}: must hold rigid transforms (rotation + translation, last row 0 0 0 1), "
                    f"deviation {err:.2g}; orthonormalise the rotations (e.g. by SVD)"
                )
        if (k[:, 0, 0] <= 0).any() or (k[:, 1, 1] <= 0).any():
            raise InputError("Rig.K: focal lengths fx = K[0,0] and fy = K[1,1] must be positive")
        if np.abs(k[:, 0, 1]).max() > 1e-9 or np.abs(k[:, 2] - [0.0, 0.0, 1.0]).max() > 1e-9 or np.abs(k[:, 1, 0]).max() > 1e-9:
            raise InputError("Rig.K: must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew: USD and glTF cannot store it)")
        size = tuple(int(s) for s in np.asarray(self.image_size).reshape(-1))
        if len(size) != 2 or min(size) <= 0:
            raise InputError(f"Rig.image_size: must be (H, W) with positive sizes, got {self.image_size}")
        self.image_size = size
        self.fps = float(self.fps)
        if not np.isfinite(self.fps) or self.fps <= 0:
            raise InputError(f"Rig.fps: must be a positive frame rate, got {self.fps}")
        if self.frame_names is None:
            self.frame_names = [f"{i:06d}" for i in range(t)]
        self.frame_names = [str(s) for s in self.frame_names]
        if len(self.frame_names) != t:
            raise InputError(f"Rig.frame_names: need one name per frame ({t}), got {len(self.frame_names)}")
        if (self.joints is None) != (self.joint_pairs is None):
            raise InputError("Rig.joints and Rig.joint_pairs: give both or neither")
        if self.joints is not None:
            j = arr("joints", np.float64, (None, 3))
            jp = arr("joint_pairs", np.int64, (j.shape[0], 2))
            if jp.size and (jp.min() < 0 or jp.max() >= b):
                raise InputError(f"Rig.joint_pairs: bone indices must lie in [0, {b})")
        if self.centres is not None:
            arr("centres", np.float64, (b, 3))
        if self.precisions is not None:
            arr("precisions", np.float64, (b, 3, 3))
        if self.lengths is not None:
            arr("lengths", np.float64, (b,))

    # ----------------------------------------------------------------- sizes and tree
    @property
    def num_frames(self) -> int:
        """T, the number of frames."""
        return int(self.bone_motion.shape[0])

    @property
    def num_bones(self) -> int:
        """B, the number of learned bones (the exported ``root`` joint not counted)."""
        return int(self.weights.shape[1])

    def bbox_diagonal(self) -> float:
        """Length of the canonical mesh's bounding-box diagonal (scene units)."""
        v = self.verts.astype(np.float64)
        return float(np.linalg.norm(v.max(0) - v.min(0)))

    def topological_order(self) -> list[int]:
        """Bone indices ordered so that every parent comes before its children (depth first).

        Raises:
            InputError: if ``parents`` contains a cycle.
        """
        b = len(self.parents)
        children: list[list[int]] = [[] for _ in range(b)]
        roots = []
        for i, p in enumerate(self.parents):
            (roots if p < 0 else children[int(p)]).append(i)
        order: list[int] = []
        stack = list(reversed(roots))
        while stack:
            i = stack.pop()
            order.append(i)
            stack.extend(reversed(children[i]))
        if len(order) != b:
            raise InputError("Rig.parents: the kinematic tree has a cycle; every bone must reach a root (-1)")
        return order

    def joint_names(self) -> list[str]:
        """Path-safe, unique bone names (letters, digits, underscore), in bone order."""
        out, seen = [], set()
        for i, name in enumerate(self.bone_names):
            s = re.sub(r"[^A-Za-z0-9_]", "_", name) or f"bone_{i:02d}"
            if s[0].isdigit():
                s = "_" + s
            if s == "root" or s in seen:
                s = f"{s}_{i}"
            seen.add(s)
            out.append(s)
        return out

    def joint_paths(self) -> list[str]:
        """UsdSkel joint path of each bone, in bone order, e.g. ``root/bone_03/bone_07``."""
        names = self.joint_names()
        paths: list[str] = [""] * self.num_bones
        for i in self.topological_order():
            p = int(self.parents[i])
            paths[i] = (paths[p] if p >= 0 else "root") + "/" + names[i]
        return paths

    # ----------------------------------------------------------------- posing (numpy float64)
    def blend_matrices(self, t: int, weights: np.ndarray | None = None) -> np.ndarray:
        """(N, 4, 4) float64 per-vertex blended transform sum_b W[n, b] A_b(t) (object frame)."""
        w = (self.weights if weights is None else weights).astype(np.float64)
        return (w @ self.bone_motion[t].reshape(self.num_bones, 16)).reshape(-1, 4, 4)

    def posed_object(self, t: int, weights: np.ndarray | None = None) -> np.ndarray:
        """(N, 3) float64 posed OBJECT-frame vertices X_n(t) = sum_b W[n, b] A_b(t) X_n.

        Args:
            t: frame index in [0, T).
            weights: optional (N, B) weights replacing ``self.weights`` (e.g. top-K pruned ones).
        """
        m = self.blend_matrices(t, weights)
        x = self.verts.astype(np.float64)
        return np.einsum("nij,nj->ni", m[:, :3, :3], x) + m[:, :3, 3]

    def posed_world(self, t: int, weights: np.ndarray | None = None) -> np.ndarray:
        """(N, 3) float64 posed vertices of frame t in the exported WORLD frame (Y up)."""
        g = self.world_from_object
        return self.posed_object(t, weights) @ g[:3, :3].T + g[:3, 3]

    def posed_world_frames(self, weights: np.ndarray | None = None) -> np.ndarray:
        """(T, N, 3) float64 :meth:`posed_world` of every frame."""
        return np.stack([self.posed_world(t, weights) for t in range(self.num_frames)])

    def posed_camera(self) -> np.ndarray:
        """(T, N, 3) float64 posed vertices in each frame's OpenCV camera frame: root_t @ X_n(t)."""
        out = np.empty((self.num_frames, self.verts.shape[0], 3))
        for t in range(self.num_frames):
            r = self.root[t]
            out[t] = self.posed_object(t) @ r[:3, :3].T + r[:3, 3]
        return out

    def project(self, cam: np.ndarray | None = None) -> np.ndarray:
        """(T, N, 2) float64 pixel coordinates (column, row) of the posed vertices, OpenCV convention.

        Args:
            cam: optional (T, N, 3) camera-frame points; defaults to :meth:`posed_camera`.
        """
        cam = self.posed_camera() if cam is None else cam
        return project_np(cam, self.K[:, None])

    def joints_camera(self) -> np.ndarray | None:
        """(T, J, 3) float64 posed joints in the OpenCV camera frame, or None without joints.

        A joint moves like a surface point at its rest position: linear blend skinning with the weights
        of the Gaussian bones there, ``softmax_b(-1/2 (X_j - C_b)^T Q_b (X_j - C_b))`` (the mesh's own
        weights), so a joint inside the body stays inside it. Without the Gaussians (``centres`` /
        ``precisions``), the equal blend of its two bones: 0.5 (A_a(t) + A_b(t)) X_j.
        """
        if self.joints is None:
            return None
        J = len(self.joints)
        if self.centres is not None and self.precisions is not None:
            d = self.joints[:, None, :] - self.centres[None]  # (J, B, 3)
            logits = -0.5 * np.einsum("jbi,bik,jbk->jb", d, self.precisions, d)
            w = np.exp(logits - logits.max(1, keepdims=True))
            w /= w.sum(1, keepdims=True)
        else:
            w = np.zeros((J, self.num_bones))
            w[np.arange(J), self.joint_pairs[:, 0]] += 0.5
            w[np.arange(J), self.joint_pairs[:, 1]] += 0.5
        out = np.empty((self.num_frames, J, 3))
        x = np.concatenate([self.joints, np.ones((J, 1))], 1)
        for t in range(self.num_frames):
            m = np.einsum("jb,bik->jik", w, self.bone_motion[t])
            xo = np.einsum("jik,jk->ji", m, x)
            out[t] = (xo @ self.root[t].T)[:, :3]
        return out

    # ----------------------------------------------------------------- exported transforms
    def bind_world(self) -> np.ndarray:
        """(B, 4, 4) float64 world rest frame of each bone: world_from_object @ bind_b."""
        return self.world_from_object @ self.bind

    def bone_world(self, t: int) -> np.ndarray:
        """(B, 4, 4) float64 world transform of each bone at frame t: G @ A_b(t) @ bind_b."""
        return self.world_from_object @ self.bone_motion[t] @ self.bind

    def local_transforms(self, world: np.ndarray) -> np.ndarray:
        """(B, 4, 4) float64 parent-relative transforms inv(parent world) @ world (root joint = identity)."""
        parent_world = np.where(
            (self.parents >= 0)[:, None, None], world[np.maximum(self.parents, 0)], np.eye(4)[None]
        )
        return np.linalg.inv(parent_world) @ world

    def camera_to_world(self) -> np.ndarray:
        """(T, 4, 4) float64 USD/glTF camera-to-world: G @ inv(root_t) @ diag(1, -1, -1, 1)."""
        return self.world_from_object @ np.linalg.inv(self.root) @ CAMERA_GL_FROM_CV


def top_k_weights(weights: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The k largest weights of every vertex, renormalised to sum to 1.

    Args:
        weights: (N, B) float weights, rows summing to 1.
        k: influences per vertex; clipped to B.

    Returns:
        (indices, values): (N, k) int64 bone indices sorted by decreasing weight and (N, k) float64
        renormalised weights. Concretely, vertex n is skinned by bones ``indices[n]`` with
        ``values[n]`` (which sum to 1).
    """
    w = np.asarray(weights, dtype=np.float64)
    k = max(1, min(int(k), w.shape[1]))
    idx = np.argsort(-w, axis=1, kind="stable")[:, :k]
    val = np.take_along_axis(w, idx, 1)
    val = val / np.maximum(val.sum(1, keepdims=True), 1e-30)
    return idx, val


def dense_weights(indices: np.ndarray, values: np.ndarray, num_bones: int) -> np.ndarray:
    """(N, B) float64 dense weights from (N, k) indices and values (the inverse of top_k_weights)."""
    out = np.zeros((indices.shape[0], num_bones))
    np.put_along_axis(out, indices, values, 1)
    return out


def top_k_error(rig: Rig, k: int) -> tuple[float, float]:
    """Largest vertex distance between full-weight and top-k posed vertices over every frame.

    Returns:
        (absolute error in scene units, error divided by the canonical bounding-box diagonal).
    """
    idx, val = top_k_weights(rig.weights, k)
    dense = dense_weights(idx, val, rig.num_bones)
    return max_distance(rig, rig.posed_world_frames(), rig.posed_world_frames(dense))


def max_distance(rig: Rig, a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Largest distance between corresponding points of a and b, and it over the bbox diagonal."""
    err = float(np.linalg.norm(a - b, axis=-1).max())
    return err, err / max(rig.bbox_diagonal(), 1e-30)


# --------------------------------------------------------------------- run directory
def save_rig(run_dir: str | os.PathLike, rig: Rig) -> None:
    """Write ``canonical.ply``, ``skeleton.json`` and ``motion.npz`` of ``rig`` into ``run_dir``.

    Each file is written to a temporary name and renamed. ``motion.npz`` also holds the evaluation
    keys: ``verts_cam`` (T, N, 3) float32 posed OpenCV-camera vertices, ``faces`` (F, 3) int32,
    ``K`` (T, 3, 3), ``image_size`` (2,) as (H, W), ``frame_names`` (T,) and, with joints,
    ``joints_cam`` (T, J, 3) float32.
    """
    run = Path(run_dir)
    run.mkdir(parents=True, exist_ok=True)
    rgba = np.concatenate([np.clip(np.round(rig.colors * 255), 0, 255), np.full((len(rig.verts), 1), 255)], 1)
    mesh = trimesh.Trimesh(rig.verts, rig.faces, vertex_colors=rgba.astype(np.uint8), process=False)
    ply = mesh.export(file_type="ply", encoding="binary")
    write_bytes(run / "canonical.ply", ply)

    bones = []
    for i, name in enumerate(rig.bone_names):
        bone = {"name": name, "parent": int(rig.parents[i]), "bind": rig.bind[i].tolist()}
        if rig.centres is not None:
            bone["centre"] = rig.centres[i].tolist()
        if rig.precisions is not None:
            bone["precision"] = rig.precisions[i].tolist()
        if rig.lengths is not None:
            bone["length"] = float(rig.lengths[i])
        bones.append(bone)
    skel = {
        "bones": bones,
        "joints": []
        if rig.joints is None
        else [{"bones": [int(a), int(b)], "position": p.tolist()} for (a, b), p in zip(rig.joint_pairs, rig.joints)],
        "root": [int(i) for i in np.flatnonzero(rig.parents < 0)],
        "world_from_object": rig.world_from_object.tolist(),
        "frame": "object (OpenCV-like, y down); bind = rigid rest frame of each bone",
    }
    write_bytes(run / "skeleton.json", json.dumps(skel, indent=1).encode())

    arrays = {
        "bone_motion": rig.bone_motion,
        "root": rig.root,
        "K": rig.K,
        "image_size": np.asarray(rig.image_size, dtype=np.int64),
        "fps": np.float64(rig.fps),
        "frame_names": np.asarray(rig.frame_names, dtype=str),
        "weights": rig.weights,
        "colors": rig.colors,
        "verts_cam": rig.posed_camera().astype(np.float32),
        "faces": rig.faces,
    }
    jc = rig.joints_camera()
    if jc is not None:
        arrays["joints_cam"] = jc.astype(np.float32)
    write_stream(run / "motion.npz", lambda f: np.savez(f, **arrays))
    logger.info("saved rig (%d vertices, %d bones, %d frames) to %s", len(rig.verts), rig.num_bones, rig.num_frames, run)


def load_rig(run_dir: str | os.PathLike) -> Rig:
    """Read the :class:`Rig` that :func:`save_rig` wrote into ``run_dir``.

    Vertex colours come from ``motion.npz`` when present (exact), else from the PLY (1/255 steps).

    Raises:
        InputError: a file is missing or malformed (the message names it).
    """
    run = Path(run_dir)
    for name in ("canonical.ply", "skeleton.json", "motion.npz"):
        if not (run / name).is_file():
            raise InputError(f"{run / name}: missing; run s3o-fit into {run} first (or point to a finished run directory)")
    try:
        mesh = trimesh.load(run / "canonical.ply", process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types on corrupt files
        raise InputError(f"{run / 'canonical.ply'}: cannot be read ({exc}); re-run the fit or restore the file") from None
    try:
        skel = json.loads((run / "skeleton.json").read_text())
        bones = skel["bones"]
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{run / 'skeleton.json'}: malformed ({exc}); re-run the fit or restore the file") from None
    try:
        with np.load(run / "motion.npz", allow_pickle=False) as z:
            mo = {k: z[k] for k in z.files}
        need = ("bone_motion", "root", "K", "image_size", "fps", "frame_names", "weights")
        missing = [k for k in need if k not in mo]
        if missing:
            raise KeyError(", ".join(missing))
    except (ValueError, KeyError, OSError) as exc:
        raise InputError(f"{run / 'motion.npz'}: malformed or missing keys ({exc}); re-run the fit") from None
    colors = mo.get("colors")
    if colors is None:
        colors = np.asarray(mesh.visual.vertex_colors)[:, :3] / 255.0

    def opt(key):
        vals = [b.get(key) for b in bones]
        return None if any(v is None for v in vals) else np.asarray(vals, dtype=np.float64)

    joints = skel.get("joints") or []
    return Rig(
        verts=np.asarray(mesh.vertices, dtype=np.float32),
        faces=np.asarray(mesh.faces, dtype=np.int32),
        colors=colors,
        weights=mo["weights"],
        bone_names=[b["name"] for b in bones],
        parents=np.asarray([b["parent"] for b in bones], dtype=np.int64),
        bind=np.asarray([b["bind"] for b in bones], dtype=np.float64),
        bone_motion=mo["bone_motion"],
        root=mo["root"],
        K=mo["K"],
        image_size=tuple(int(s) for s in mo["image_size"]),
        fps=float(mo["fps"]),
        frame_names=[str(s) for s in mo["frame_names"]],
        world_from_object=np.asarray(skel.get("world_from_object", Y_UP_FROM_OPENCV), dtype=np.float64),
        joints=np.asarray([j["position"] for j in joints], dtype=np.float64) if joints else None,
        joint_pairs=np.asarray([j["bones"] for j in joints], dtype=np.int64) if joints else None,
        centres=opt("centre"),
        precisions=opt("precision"),
        lengths=opt("length"),
    )


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, 3) float32 unit area-weighted vertex normals (trimesh); +Y for vertices in no face."""
    n = np.array(trimesh.Trimesh(points, faces, process=False).vertex_normals, dtype=np.float64)
    bad = ~(np.abs(np.linalg.norm(n, axis=1) - 1.0) < 1e-3)  # vertices in no face: any unit vector
    n[bad] = (0.0, 1.0, 0.0)
    return n.astype(np.float32)


def decompose_rigid(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translations and unit quaternions of rigid transforms.

    Args:
        m: (..., 4, 4) float64 rigid transforms.

    Returns:
        (translation (..., 3), quaternion (..., 4) as x, y, z, w with w >= 0 for the first element
        of the last-but-one axis and sign continuity along it, so that interpolation between
        consecutive time samples takes the short way).
    """
    shape = m.shape[:-2]
    q = Rotation.from_matrix(m[..., :3, :3].reshape(-1, 3, 3)).as_quat().reshape(*shape, 4)
    if q.ndim >= 2 and q.shape[0] > 1:  # time axis first: keep consecutive samples on one hemisphere
        for i in range(1, q.shape[0]):
            flip = (q[i] * q[i - 1]).sum(-1) < 0
            q[i][flip] *= -1
    return m[..., :3, 3].copy(), q
