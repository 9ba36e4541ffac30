"""What the evaluation tests share: a small moving, articulated scene (a body box and a swinging leg box,
translating and turning), the loop twin of PCK-T and a minimal ``motion.npz``."""

from __future__ import annotations

import math

import numpy as np
import trimesh

H, W = 56, 72
F_PX = 100.0


def rot(axis, a):
    c, s = math.cos(a), math.sin(a)
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def two_box_sequence(T=5):
    """verts (T, 16, 3), faces (24, 3), joints (T, 3, 3), K (3, 3): OpenCV camera space, y down."""
    body = trimesh.creation.box(extents=(1.0, 0.4, 0.4))
    leg = trimesh.creation.box(extents=(0.2, 0.6, 0.2))
    leg_v = np.asarray(leg.vertices) + [0.0, 0.3, 0.0]  # hangs down (+y) from its hinge
    hinge = np.array([0.35, 0.2, 0.0])
    faces = np.concatenate([body.faces, leg.faces + len(body.vertices)]).astype(np.int32)
    verts, joints = [], []
    for t in range(T):
        Rl = rot("z", 0.6 * math.sin(1.3 * t))
        obj = np.concatenate([body.vertices, leg_v @ Rl.T + hinge])
        jo = np.stack([np.zeros(3), hinge, hinge + Rl @ [0.0, 0.6, 0.0]])
        Rr, tr = rot("y", 0.12 * t), np.array([-0.4 + 0.2 * t, -0.1, 4.0])
        verts.append(obj @ Rr.T + tr)
        joints.append(jo @ Rr.T + tr)
    K = np.array([[F_PX, 0, W / 2 - 0.5], [0, F_PX, H / 2 - 0.5], [0, 0, 1]], np.float32)
    return np.array(verts, np.float32), faces, np.array(joints, np.float32), K


def cam_from_world(T=5):
    """(T, 4, 4) world -> camera transforms of :func:`two_box_sequence` (world: +y up, the boxes' y flipped)."""
    flip = np.diag([1.0, -1.0, -1.0])  # a half turn about x: the object frame's y is down, the world's up
    m = np.tile(np.eye(4), (T, 1, 1))
    for t in range(T):
        m[t, :3, :3] = rot("y", 0.12 * t) @ flip
        m[t, :3, 3] = [-0.4 + 0.2 * t, -0.1, 4.0]
    return m


def _proj(K, X):
    p = K @ X
    return p[:2] / p[2]


def naive_pckt(kp, face_index, bary, verts, faces, K, area, alpha=0.2, threshold_frame="reference"):
    """Loops over pairs, keypoints and pixels, as LASR's eval_badja.py does it (one pair at a time)."""
    A, P = kp.shape[:2]
    pred = np.zeros((A, A, P, 2))
    correct = total = 0
    for i in range(A):
        fg = [(r, c) for r in range(face_index.shape[1]) for c in range(face_index.shape[2]) if face_index[i, r, c] >= 0]
        for j in range(A):
            if i == j:
                continue
            for p in range(P):
                x, y = kp[i, p, :2]
                if fg:
                    r, c = min(fg, key=lambda rc: (rc[1] - x) ** 2 + (rc[0] - y) ** 2)
                    f, b = face_index[i, r, c], bary[i, r, c].astype(np.float64)
                    Xi = sum(b[k] * verts[i, faces[f, k]].astype(np.float64) for k in range(3))
                    Xj = sum(b[k] * verts[j, faces[f, k]].astype(np.float64) for k in range(3))
                    pred[i, j, p] = kp[i, p, :2] + _proj(K[j], Xj) - _proj(K[i], Xi)
                else:
                    pred[i, j, p] = kp[i, p, :2]
                if kp[i, p, 2] > 0.5 and kp[j, p, 2] > 0.5:
                    total += 1
                    thr = alpha * math.sqrt(area[i] if threshold_frame == "reference" else area[j])
                    correct += np.linalg.norm(pred[i, j, p] - kp[j, p, :2]) < thr
    return correct, total, pred


def tiny_motion(path, **over):
    """A two-frame, one-triangle ``motion.npz`` at ``path``; ``over`` replaces keys (None drops one)."""
    T = 2
    d = dict(verts_cam=np.ones((T, 3, 3), np.float32), faces=np.array([[0, 1, 2]], np.int32), K=np.eye(3, dtype=np.float32),
             image_size=np.array([4, 5]), frame_names=np.array(["a", "b"]))
    d.update(over)
    d = {k: v for k, v in d.items() if v is not None}
    np.savez(path, **d)
    return path
