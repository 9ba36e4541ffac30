"""A procedural long-bodied animal: a lizard (a long spine and tail, four short sprawling legs) that crawls
with lateral undulation.

Object frame as the quadruped's (:mod:`s3o_warp.synth.quadruped`): +y up, +x forward, +z to the animal's
right, metres, ground at y = 0. Snout to tail tip about 1.6, the body's axis 0.1 above the ground. The
skeleton has 24 joints: a spine chain from the pelvis (root) forward (spine_2, spine_1, chest, neck, head,
snout) and back (tail_1 .. tail_4, tail_tip), and four two-segment legs that leave the body sideways
(shoulder -> elbow -> foot in front, hip -> knee -> foot behind; suffixes ``fl``, ``fr``, ``bl``, ``br`` with
left = -z). The skin is made like the quadruped's (a smooth union of capsules and ellipsoids, marching cubes,
Taubin smoothing; distance-based skinning weights).

The crawl: a wave of sideways bending runs from the neck to the tail tip (a yaw of every spine joint, the
curvature ``A sin(2 pi (t / period - s / wavelength))`` at arclength ``s``, growing toward the tail and
small at the head, which keeps looking ahead), the legs step in diagonal pairs (front-left with
back-right), each upper leg sweeping forward and back in the horizontal plane and lifting in its swing, and
the body moves forward along +x. Deterministic given the seed (proportions +-5 %, period +-10 %, phase).
"""

from __future__ import annotations

import math

import numpy as np

from .model import AnimatedMesh
from .quadruped import _mesh_from_sdf, _rot, check_build, nearest_surface_vertices, posed_model, skinning_weights

# name, parent name, rest position (x forward, y up, z right), metres.
_SPINE: list[tuple[str, str | None, tuple[float, float, float]]] = [
    ("pelvis", None, (-0.15, 0.10, 0.0)),
    ("spine_2", "pelvis", (0.00, 0.10, 0.0)),
    ("spine_1", "spine_2", (0.15, 0.10, 0.0)),
    ("chest", "spine_1", (0.28, 0.10, 0.0)),
    ("neck", "chest", (0.38, 0.11, 0.0)),
    ("head", "neck", (0.46, 0.12, 0.0)),
    ("snout", "head", (0.60, 0.10, 0.0)),
    ("tail_1", "pelvis", (-0.30, 0.095, 0.0)),
    ("tail_2", "tail_1", (-0.48, 0.085, 0.0)),
    ("tail_3", "tail_2", (-0.66, 0.07, 0.0)),
    ("tail_4", "tail_3", (-0.84, 0.055, 0.0)),
    ("tail_tip", "tail_4", (-1.02, 0.04, 0.0)),
]
_LEGS: list[tuple[str, str | None, tuple[float, float, float]]] = []
for _leg, _sz in (("fl", -1.0), ("fr", 1.0), ("bl", -1.0), ("br", 1.0)):
    _front = _leg[0] == "f"
    _up, _mid, _girdle, _x = ("shoulder", "elbow", "chest", 0.28) if _front else ("hip", "knee", "pelvis", -0.15)
    _LEGS += [
        (f"{_up}_{_leg}", _girdle, (_x, 0.09, 0.06 * _sz)),
        (f"{_mid}_{_leg}", f"{_up}_{_leg}", (_x + (0.02 if _front else -0.03), 0.08, 0.17 * _sz)),
        (f"foot_{_leg}", f"{_mid}_{_leg}", (_x + (0.05 if _front else 0.0), 0.012, 0.21 * _sz)),
    ]
_JOINTS = _SPINE + _LEGS
JOINT_NAMES = [j[0] for j in _JOINTS]
LEGS = ("fl", "fr", "bl", "br")
# the spine from the snout back to the tail tip (the wave's arclength runs along it)
_AXIS = ["snout", "head", "neck", "chest", "spine_1", "spine_2", "pelvis", "tail_1", "tail_2", "tail_3", "tail_4",
         "tail_tip"]
# body radius at each joint of _AXIS (capsules taper between them)
_RADII = [0.02, 0.045, 0.048, 0.062, 0.068, 0.068, 0.062, 0.05, 0.038, 0.028, 0.018, 0.01]

# Keypoints: name, joint, offset from the joint (m) toward which the nearest rest surface vertex is taken.
_KEYPOINTS: list[tuple[str, str, tuple[float, float, float]]] = [
    ("snout", "snout", (0.05, 0.0, 0.0)),
    ("head", "head", (0.0, 0.1, 0.0)),
    ("neck", "neck", (0.0, 0.1, 0.0)),
    ("chest", "chest", (0.0, 0.1, 0.0)),
    ("mid_back", "spine_1", (0.0, 0.1, 0.0)),
    ("pelvis", "pelvis", (0.0, 0.1, 0.0)),
    ("tail_1", "tail_1", (0.0, 0.1, 0.0)),
    ("tail_2", "tail_2", (0.0, 0.1, 0.0)),
    ("tail_3", "tail_3", (0.0, 0.1, 0.0)),
    ("tail_tip", "tail_tip", (-0.05, 0.0, 0.0)),
]
for _leg, _sz in (("fl", -1.0), ("fr", 1.0), ("bl", -1.0), ("br", 1.0)):
    _up, _mid = ("shoulder", "elbow") if _leg[0] == "f" else ("hip", "knee")
    _KEYPOINTS += [
        (f"{_up}_{_leg}", f"{_up}_{_leg}", (0.0, 0.1, 0.0)),
        (f"{_mid}_{_leg}", f"{_mid}_{_leg}", (0.0, 0.0, 0.1 * _sz)),
        (f"foot_{_leg}", f"foot_{_leg}", (0.02, -0.05, 0.03 * _sz)),
    ]
KEYPOINT_NAMES = [k[0] for k in _KEYPOINTS]


def _primitives(p: dict[str, np.ndarray], s: np.ndarray):
    """Capsules along the spine (radii ``_RADII`` times the girth factor), a head, and the legs."""
    prims = []
    for k in range(len(_AXIS) - 1):
        r0, r1 = _RADII[k] * s[1], _RADII[k + 1] * s[1]
        prims.append(("cap", p[_AXIS[k]], p[_AXIS[k + 1]], r0, r1))
    prims.append(("ell", p["head"] + [0.02, 0.0, 0.0], (0.08, 0.042 * s[1], 0.05 * s[1])))
    for leg in LEGS:
        up, mid = ("shoulder", "elbow") if leg[0] == "f" else ("hip", "knee")
        prims.append(("cap", p[f"{up}_{leg}"], p[f"{mid}_{leg}"], 0.026 * s[3], 0.02 * s[3]))
        prims.append(("cap", p[f"{mid}_{leg}"], p[f"foot_{leg}"], 0.02 * s[3], 0.015 * s[3]))
        prims.append(("ell", p[f"foot_{leg}"] + [0.02, 0.0, 0.0], (0.035, 0.012, 0.025)))
    return prims


def crawl_cycle(num_frames: int, fps: float, period: float, phase: float, rest_joints: np.ndarray,
                stride: float) -> tuple[np.ndarray, np.ndarray]:
    """Local joint rotations and root translation of the crawl.

    Returns:
        rot: (T, J, 3, 3) local rotation of each joint about its own rest position.
        root_shift: (T, 3) translation of the whole body (forward motion), metres.
    """
    t = np.arange(num_frames) / fps
    ph = 2 * np.pi * (t / period + phase)
    idx = {n: i for i, n in enumerate(JOINT_NAMES)}
    rot = np.tile(np.eye(3), (num_frames, len(JOINT_NAMES), 1, 1))
    axis = rest_joints[[idx[n] for n in _AXIS]]
    seg = np.linalg.norm(np.diff(axis, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])  # arclength from the snout
    length = float(arc[-1])
    pelvis_at = _AXIS.index("pelvis")
    for k, name in enumerate(_AXIS[1:-1], start=1):  # every joint between the snout and the tail tip
        if name == "pelvis":
            continue  # the root: the body's heading stays along +x
        amp = 0.8 * (0.25 + 1.25 * arc[k] / length)  # rad / m: a small bend at the neck, a large one in the tail
        bend = amp * np.sin(ph - 2 * np.pi * arc[k] / length) * 0.5 * (seg[k - 1] + seg[k])
        # a joint in front of the pelvis turns what lies ahead of it, one behind turns what lies behind:
        # the same sign of curvature along the body needs opposite turns
        rot[:, idx[name]] = _rot("y", -bend if k < pelvis_at else bend)
    sweep, lift = math.radians(30.0), math.radians(25.0)
    for leg, off in (("fl", 0.0), ("br", 0.0), ("fr", np.pi), ("bl", np.pi)):
        up, mid = ("shoulder", "elbow") if leg[0] == "f" else ("hip", "knee")
        side = -1.0 if leg[1] == "l" else 1.0
        a = ph + off
        swing = np.maximum(0.0, np.cos(a))
        # forward (+x) in the swing half, backward in the stance half; the foot lifts while it swings
        yaw = _rot("y", side * sweep * np.sin(a))
        rot[:, idx[f"{up}_{leg}"]] = yaw @ _rot("x", -side * lift * swing)
        rot[:, idx[f"{mid}_{leg}"]] = _rot("x", side * 0.5 * lift * swing)
    root = np.zeros((num_frames, 3))
    root[:, 0] = stride * t / period
    return rot, root


def build_lizard(frames: int = 48, fps: float = 24.0, seed: int = 0, target_vertices: int = 3000) -> AnimatedMesh:
    """Build the procedural lizard and sample its crawl.

    Args:
        frames: T, the number of frames to sample (>= 1).
        fps: frames per second (> 0).
        seed: fixes proportions, crawl period and phase.
        target_vertices: approximate vertex count of the skin (the result lands within about 25 %).

    Returns:
        An :class:`AnimatedMesh` in the object frame (+y up, +x forward, metres), clip "crawl".

    Raises:
        InputError: for a non-positive frame count, fps or vertex target.
    """
    check_build("lizard", frames, fps, target_vertices)
    rng = np.random.default_rng(seed)
    scale = 1.0 + rng.uniform(-0.05, 0.05, size=4)  # body length, girth, tail, legs
    period = 1.2 * (1.0 + rng.uniform(-0.1, 0.1))
    phase = float(rng.uniform(0.0, 1.0))

    parents = np.array([-1 if p is None else JOINT_NAMES.index(p) for _, p, _ in _JOINTS], dtype=np.int32)
    rest_joints = np.array([pos for _, _, pos in _JOINTS], dtype=np.float64)
    tail = [i for i, n in enumerate(JOINT_NAMES) if n.startswith("tail")]
    rest_joints[:, 0] *= scale[0]
    rest_joints[tail, 0] = -0.15 * scale[0] + (rest_joints[tail, 0] + 0.15 * scale[0]) * scale[2]
    legs = [i for i, n in enumerate(JOINT_NAMES) if n.split("_")[0] in ("elbow", "knee", "foot")]
    rest_joints[legs, 2] *= scale[3]
    pos = {n: rest_joints[i] for i, n in enumerate(JOINT_NAMES)}

    verts, faces = _mesh_from_sdf(_primitives(pos, scale), target_vertices, lo=(-1.15, -0.03, -0.3),
                                  hi=(0.72, 0.22, 0.3), area=0.55)
    weights = skinning_weights(verts, rest_joints, parents)
    reach = float(np.linalg.norm(pos["foot_fl"] - pos["shoulder_fl"]))
    rot, root_shift = crawl_cycle(frames, fps, period, phase, rest_joints, stride=2.0 * reach * math.sin(math.radians(30.0)))
    return posed_model("lizard", "crawl", seed, JOINT_NAMES, parents, rest_joints, verts, faces, weights, rot,
                       root_shift, fps, _scale_colours(verts, rng))


def _scale_colours(verts: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """sRGB base colours: an olive back, a pale belly (below the body's axis), seeded hue jitter."""
    back = np.array([0.36, 0.45, 0.22]) * (1.0 + rng.uniform(-0.08, 0.08, size=3))
    belly = np.clip((0.09 - verts[:, 1]) / 0.04, 0.0, 1.0)[:, None]
    return np.clip(back * (1 - belly) + np.array([0.78, 0.74, 0.55]) * belly, 0.0, 1.0).astype(np.float32)


def lizard_keypoints(mesh: AnimatedMesh) -> tuple[list[str], np.ndarray]:
    """Anatomical keypoints of the lizard as rest-mesh vertex indices (22: the spine's top line from the
    snout to the tail tip, and per leg its top, its elbow or knee (outer side) and its foot (the sole))."""
    return KEYPOINT_NAMES.copy(), nearest_surface_vertices(mesh, JOINT_NAMES, _KEYPOINTS)
