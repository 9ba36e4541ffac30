"""A procedural, articulated quadruped with a walk cycle: the embedded default sequence.

Object frame: +y up, +x forward (the animal faces +x), +z to the animal's right, metres, ground at
y = 0, body length (nose to tail tip) about 1.4 and body (withers to rump) about 0.6. The skeleton
has 23 joints: a spine chain (pelvis root, spine, withers, neck, head), end joints (nose, ear tips,
feet, tail tip) and four two-segment legs (shoulder/hip -> knee -> foot). Suffixes ``_l``/``_r``
are the animal's left (-z) and right (+z); legs are ``fl``, ``fr`` (front) and ``bl``, ``br`` (back).

The skin is the marching-cubes surface of a smooth union of ellipsoids and tapered capsules, smoothed
with Taubin's filter; skinning weights come from the distance to each bone segment (a softmax, top 4
kept, renormalised), and a bone moves with its parent joint's transform. The walk is a diagonal
gait (front-left with back-right, front-right with back-left), knees flexing
in the swing phase, head bobbing twice per cycle, tail swaying, the root moving forward (or in place).
Everything is deterministic given the seed (proportions +-5 %, gait period +-10 %, phase).
"""

from __future__ import annotations

import logging
import math

import numpy as np
import trimesh
from skimage import measure

from ..errors import InputError
from .model import AnimatedMesh

log = logging.getLogger(__name__)

# name, parent name, rest position (x forward, y up, z right), metres.
_JOINTS: list[tuple[str, str | None, tuple[float, float, float]]] = [
    ("pelvis", None, (-0.30, 0.62, 0.0)),
    ("spine", "pelvis", (0.00, 0.64, 0.0)),
    ("withers", "spine", (0.28, 0.67, 0.0)),
    ("neck", "withers", (0.38, 0.72, 0.0)),
    ("head", "neck", (0.53, 0.88, 0.0)),
    ("nose", "head", (0.71, 0.82, 0.0)),
    ("ear_l", "head", (0.49, 1.03, -0.07)),
    ("ear_r", "head", (0.49, 1.03, 0.07)),
    ("shoulder_fl", "withers", (0.28, 0.56, -0.12)),
    ("knee_fl", "shoulder_fl", (0.30, 0.30, -0.12)),
    ("foot_fl", "knee_fl", (0.28, 0.04, -0.12)),
    ("shoulder_fr", "withers", (0.28, 0.56, 0.12)),
    ("knee_fr", "shoulder_fr", (0.30, 0.30, 0.12)),
    ("foot_fr", "knee_fr", (0.28, 0.04, 0.12)),
    ("hip_bl", "pelvis", (-0.30, 0.56, -0.12)),
    ("knee_bl", "hip_bl", (-0.25, 0.31, -0.12)),
    ("foot_bl", "knee_bl", (-0.32, 0.04, -0.12)),
    ("hip_br", "pelvis", (-0.30, 0.56, 0.12)),
    ("knee_br", "hip_br", (-0.25, 0.31, 0.12)),
    ("foot_br", "knee_br", (-0.32, 0.04, 0.12)),
    ("tail_base", "pelvis", (-0.44, 0.67, 0.0)),
    ("tail_mid", "tail_base", (-0.58, 0.62, 0.0)),
    ("tail_tip", "tail_mid", (-0.72, 0.52, 0.0)),
]
JOINT_NAMES = [j[0] for j in _JOINTS]
LEGS = ("fl", "fr", "bl", "br")

# Anatomical keypoints: name, joint, offset from the joint (m) toward which the nearest surface
# vertex of the rest mesh is taken (offsets push to the visible side: down for feet, out for knees).
_KEYPOINTS: list[tuple[str, str, tuple[float, float, float]]] = [
    ("nose", "nose", (0.05, 0.0, 0.0)),
    ("ear_tip_l", "ear_l", (0.0, 0.05, -0.02)),
    ("ear_tip_r", "ear_r", (0.0, 0.05, 0.02)),
    ("withers", "withers", (0.0, 0.25, 0.0)),
    ("throat", "neck", (0.12, -0.05, 0.0)),
    ("tail_base", "tail_base", (0.0, 0.1, 0.0)),
    ("tail_tip", "tail_tip", (0.0, 0.0, 0.0)),
]
for _leg, _side in (("fl", -1.0), ("fr", 1.0), ("bl", -1.0), ("br", 1.0)):
    _up = "shoulder" if _leg[0] == "f" else "hip"
    _KEYPOINTS += [
        (f"{_up}_{_leg}", f"{_up}_{_leg}", (0.0, 0.0, 0.25 * _side)),
        (f"knee_{_leg}", f"knee_{_leg}", (0.0, 0.0, 0.25 * _side)),
        (f"foot_{_leg}", f"foot_{_leg}", (0.03, -0.1, 0.05 * _side)),
    ]
KEYPOINT_NAMES = [k[0] for k in _KEYPOINTS]


def _sdf_ellipsoid(p: np.ndarray, centre, radii) -> np.ndarray:
    """Approximate signed distance to an axis-aligned ellipsoid (scaled-sphere bound)."""
    q = (p - np.asarray(centre)) / np.asarray(radii)
    return (np.linalg.norm(q, axis=-1) - 1.0) * min(radii)


def _sdf_capsule(p: np.ndarray, a, b, ra: float, rb: float) -> np.ndarray:
    """Approximate signed distance to a capsule from ``a`` to ``b`` with radius tapering ra -> rb."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    ab = b - a
    t = np.clip(((p - a) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
    d = np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)
    return d - (ra + (rb - ra) * t)


def _smooth_union(d1: np.ndarray, d2: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum of two distance fields (blend radius ``k``)."""
    h = np.clip(0.5 + 0.5 * (d2 - d1) / k, 0.0, 1.0)
    return d2 * (1 - h) + d1 * h - k * h * (1 - h)


def _primitives(p: dict[str, np.ndarray], s: np.ndarray):
    """The body's primitives from joint positions ``p`` and per-part size factors ``s``."""
    prims = [
        ("ell", (0.0, 0.63, 0.0), (0.42 * s[0], 0.16 * s[1], 0.145 * s[1])),
        ("ell", (0.22, 0.64, 0.0), (0.18, 0.165 * s[1], 0.15 * s[1])),
        ("ell", (-0.27, 0.62, 0.0), (0.16, 0.15 * s[1], 0.14 * s[1])),
        ("cap", p["withers"] + [0.04, 0.0, 0.0], p["head"], 0.10 * s[2], 0.065 * s[2]),
        ("ell", p["head"], (0.11, 0.08, 0.075)),
        ("cap", p["head"], p["nose"], 0.06, 0.035),
    ]
    for side in ("l", "r"):
        base = p["head"] + [-0.03, 0.06, 0.04 if side == "r" else -0.04]
        prims.append(("cap", base, p[f"ear_{side}"], 0.032, 0.016))
    for leg in LEGS:
        up = "shoulder" if leg[0] == "f" else "hip"
        prims.append(("cap", p[f"{up}_{leg}"], p[f"knee_{leg}"], 0.065 * s[3], 0.042 * s[3]))
        prims.append(("cap", p[f"knee_{leg}"], p[f"foot_{leg}"], 0.042 * s[3], 0.03 * s[3]))
        prims.append(("ell", p[f"foot_{leg}"] + [0.015, -0.005, 0.0], (0.045, 0.035, 0.035)))
    prims.append(("cap", p["tail_base"] + [0.05, 0.0, 0.0], p["tail_mid"], 0.045, 0.03))
    prims.append(("cap", p["tail_mid"], p["tail_tip"], 0.03, 0.012))
    return prims


def _body_sdf(points: np.ndarray, prims, blend: float) -> np.ndarray:
    d = None
    for prim in prims:
        di = _sdf_ellipsoid(points, *prim[1:]) if prim[0] == "ell" else _sdf_capsule(points, *prim[1:])
        d = di if d is None else _smooth_union(d, di, blend)
    return d


def _point_segment_distance(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(V,) distances from points x (V, 3) to the segment a-b."""
    ab = b - a
    t = np.clip(((x - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(x - (a + t[:, None] * ab), axis=-1)


def skinning_weights(verts: np.ndarray, joints: np.ndarray, parents: np.ndarray, tau: float = 0.015,
                     top_k: int = 4) -> np.ndarray:
    """Weights from distance to bone segments (parent joint -> child joint), owned by the parent.

    Args:
        verts: (V, 3) rest vertices.
        joints: (J, 3) rest joint positions.
        parents: (J,) parent indices, -1 for the root.
        tau: softmax temperature in metres on the distance (smaller = sharper).
        top_k: influences kept per vertex (then renormalised).

    Returns:
        float32 (V, J) weights; each row sums to 1; leaf joints own no bone and get zero weight.
    """
    children = [c for c in range(len(parents)) if parents[c] >= 0]
    dist = np.stack([_point_segment_distance(verts, joints[parents[c]], joints[c]) for c in children], 1)
    logits = -(dist - dist.min(1, keepdims=True)) / tau
    seg_w = np.exp(logits)
    w = np.zeros((verts.shape[0], len(parents)))
    for k, c in enumerate(children):
        w[:, parents[c]] += seg_w[:, k]
    if top_k < w.shape[1]:
        keep = np.argpartition(w, -top_k, axis=1)[:, -top_k:]
        kept = np.zeros_like(w)
        np.put_along_axis(kept, keep, np.take_along_axis(w, keep, axis=1), axis=1)
        w = kept
    return (w / w.sum(1, keepdims=True)).astype(np.float32)


def _rot(axis: str, angle: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rotations about a principal axis by ``angle`` (T,) radians."""
    c, s = np.cos(angle), np.sin(angle)
    o, z = np.ones_like(angle), np.zeros_like(angle)
    if axis == "z":
        m = [[c, -s, z], [s, c, z], [z, z, o]]
    elif axis == "y":
        m = [[c, z, s], [z, o, z], [-s, z, c]]
    else:
        m = [[o, z, z], [z, c, -s], [z, s, c]]
    return np.moveaxis(np.array(m), (0, 1), (-2, -1))


def walk_cycle(num_frames: int, fps: float, period: float, phase: float, in_place: bool,
               stride: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local joint rotations and root translation of the walk.

    Returns:
        rot: (T, J, 3, 3) local rotation of each joint about its own rest position.
        root_shift: (T, 3) translation of the whole body (forward motion and bob), metres.
        times: (T,) seconds.
    """
    t = np.arange(num_frames) / fps
    ph = 2 * np.pi * (t / period + phase)
    nj = len(JOINT_NAMES)
    rot = np.tile(np.eye(3), (num_frames, nj, 1, 1))
    idx = {n: i for i, n in enumerate(JOINT_NAMES)}
    swing = math.radians(24.0)
    for leg, off in (("fl", 0.0), ("br", 0.0), ("fr", np.pi), ("bl", np.pi)):
        up = "shoulder" if leg[0] == "f" else "hip"
        a = ph + off
        rot[:, idx[f"{up}_{leg}"]] = _rot("z", swing * np.sin(a))
        flex = math.radians(45.0 if leg[0] == "f" else 35.0) * np.maximum(0.0, np.cos(a)) ** 1.5
        rot[:, idx[f"knee_{leg}"]] = _rot("z", -flex)
    rot[:, idx["neck"]] = _rot("z", math.radians(5.0) * np.sin(2 * ph))
    rot[:, idx["head"]] = _rot("z", math.radians(-4.0) * np.sin(2 * ph + 0.6))
    rot[:, idx["spine"]] = _rot("y", math.radians(3.0) * np.sin(ph))
    rot[:, idx["tail_base"]] = _rot("y", math.radians(18.0) * np.sin(ph)) @ _rot("z", np.full_like(ph, 0.2))
    rot[:, idx["tail_mid"]] = _rot("y", math.radians(22.0) * np.sin(ph - 0.7))
    rot[:, idx["pelvis"]] = _rot("x", math.radians(2.0) * np.sin(ph))
    root = np.zeros((num_frames, 3))
    root[:, 1] = 0.012 * np.cos(2 * ph)
    if not in_place:
        root[:, 0] = stride * t / period
    return rot, root, t


def forward_kinematics(rest_joints: np.ndarray, parents: np.ndarray, rot: np.ndarray,
                       root_shift: np.ndarray) -> np.ndarray:
    """Global 4x4 transforms (T, J, 4, 4) mapping rest space to posed space for each joint.

    Joint j rotates by ``rot[:, j]`` about its rest position, then follows its parent's transform;
    the root additionally translates by ``root_shift``.
    """
    num_t, nj = rot.shape[:2]
    g = np.zeros((num_t, nj, 4, 4))
    for j in range(nj):
        local = np.tile(np.eye(4), (num_t, 1, 1))
        local[:, :3, :3] = rot[:, j]
        local[:, :3, 3] = rest_joints[j] - rot[:, j] @ rest_joints[j]
        if parents[j] < 0:
            local[:, :3, 3] += root_shift
            g[:, j] = local
        else:
            g[:, j] = g[:, parents[j]] @ local
    return g


def build_quadruped(frames: int = 48, fps: float = 24.0, seed: int = 0, target_vertices: int = 3000,
                    in_place: bool = False) -> AnimatedMesh:
    """Build the procedural quadruped and sample its walk.

    Args:
        frames: T, the number of frames to sample (>= 1).
        fps: frames per second (> 0).
        seed: fixes proportions, gait period and phase.
        target_vertices: approximate vertex count of the skin (the result lands within about 25 %).
        in_place: walk on the spot instead of moving forward along +x.

    Returns:
        An :class:`AnimatedMesh` in the object frame of this module (+y up, +x forward, metres).

    Raises:
        InputError: for a non-positive frame count, fps or vertex target.
    """
    check_build("quadruped", frames, fps, target_vertices)
    rng = np.random.default_rng(seed)
    scale = 1.0 + rng.uniform(-0.05, 0.05, size=4)  # body length, girth, neck, legs
    period = 1.0 * (1.0 + rng.uniform(-0.1, 0.1))
    phase = float(rng.uniform(0.0, 1.0))

    parents = np.array([-1 if p is None else JOINT_NAMES.index(p) for _, p, _ in _JOINTS], dtype=np.int32)
    rest_joints = np.array([pos for _, _, pos in _JOINTS], dtype=np.float64)
    rest_joints[:, 0] *= scale[0]
    legs = [i for i, n in enumerate(JOINT_NAMES) if n.split("_")[0] in ("knee", "foot")]
    rest_joints[legs, 1] = 0.04 + (rest_joints[legs, 1] - 0.04) * scale[3]
    pos = {n: rest_joints[i] for i, n in enumerate(JOINT_NAMES)}

    prims = _primitives(pos, scale)
    verts, faces = _mesh_from_sdf(prims, target_vertices)
    weights = skinning_weights(verts, rest_joints, parents)

    leg_len = float(np.linalg.norm(pos["shoulder_fl"] - pos["knee_fl"]) + np.linalg.norm(pos["knee_fl"] - pos["foot_fl"]))
    stride = 2.0 * leg_len * math.sin(math.radians(24.0))
    rot, root_shift, _ = walk_cycle(frames, fps, period, phase, in_place, stride)
    return posed_model("quadruped", "walk", seed, JOINT_NAMES, parents, rest_joints, verts, faces, weights, rot,
                       root_shift, fps, _coat_colours(verts, rest_joints, rng))


def check_build(what: str, frames: int, fps: float, target_vertices: int) -> None:
    """Refuse a procedural model's impossible settings (``what``: its name) with one line naming the fix."""
    if frames < 1:
        raise InputError(f"synthetic {what}: frames must be >= 1, got {frames}; pass --frames N with N >= 1")
    if fps <= 0:
        raise InputError(f"synthetic {what}: fps must be > 0, got {fps}; pass --fps F with F > 0")
    if target_vertices < 200:
        raise InputError(f"synthetic {what}: target_vertices must be >= 200, got {target_vertices}")


def posed_model(what: str, clip: str, seed: int, joint_names: list[str], parents: np.ndarray, rest_joints: np.ndarray,
                verts: np.ndarray, faces: np.ndarray, weights: np.ndarray, rot: np.ndarray, root_shift: np.ndarray,
                fps: float, colors: np.ndarray) -> AnimatedMesh:
    """A procedural model posed by its motion: forward kinematics of the local rotations ``rot`` (T, J, 3, 3) and
    ``root_shift`` (T, 3) (:func:`forward_kinematics`), linear blend skinning of the rest skin ``verts`` (V, 3)."""
    g = forward_kinematics(rest_joints, parents, rot, root_shift)  # (T, J, 4, 4)
    blend = np.einsum("vj,tjab->tvab", weights, g[:, :, :3, :], optimize=True)  # (T, V, 3, 4)
    posed = np.einsum("tvab,vb->tva", blend[..., :3], verts) + blend[..., 3]
    joints = np.einsum("tjab,jb->tja", g[:, :, :3, :3], rest_joints) + g[:, :, :3, 3]
    return AnimatedMesh(
        rest_verts=verts.astype(np.float32),
        faces=faces.astype(np.int32),
        verts=posed.astype(np.float32),
        joint_names=list(joint_names),
        parents=parents,
        joints=joints.astype(np.float32),
        deforming=np.ones(len(joint_names), dtype=bool),
        weights=weights,
        rest_joints=rest_joints.astype(np.float32),
        fps=float(fps),
        clip_names=[clip],
        clip=clip,
        colors=colors,
        source=f"procedural {what} (seed {seed})",
    )


def _mesh_from_sdf(prims, target_vertices: int, lo=(-0.85, -0.05, -0.25), hi=(0.85, 1.15, 0.25),
                   area: float = 1.9) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of the smooth union, the largest component, Taubin-smoothed, ~target vertices.

    ``lo``, ``hi``: the grid's corners (metres, the body inside them); ``area``: the skin's area near the
    default proportions (m^2), which sets the first voxel size."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    h = math.sqrt(area / (1.9 * target_vertices))
    for _ in range(3):
        shape = np.ceil((hi - lo) / h).astype(int) + 1
        axes = [lo[k] + h * np.arange(shape[k]) for k in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        sdf = _body_sdf(grid, prims, blend=0.035).reshape(shape)
        verts, faces, _, _ = measure.marching_cubes(sdf, level=0.0, spacing=(h, h, h))
        ratio = len(verts) / target_vertices
        if 0.8 < ratio < 1.25:
            break
        h *= math.sqrt(ratio)
    mesh = trimesh.Trimesh(verts + lo, faces, process=True)
    parts = mesh.split(only_watertight=False)
    if len(parts) > 1:
        mesh = max(parts, key=lambda m: len(m.vertices))
    trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=-0.53, iterations=6)
    mesh.fix_normals()
    log.debug("procedural skin: %d vertices, %d faces (voxel %.4f m)", len(mesh.vertices), len(mesh.faces), h)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def _coat_colours(verts: np.ndarray, joints: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """sRGB base colours: a warm coat, darker legs toward the feet, lighter belly, seeded hue jitter."""
    base = np.array([0.62, 0.43, 0.27]) * (1.0 + rng.uniform(-0.08, 0.08, size=3))
    y = verts[:, 1]
    leg_dark = np.clip((0.35 - y) / 0.3, 0.0, 1.0)[:, None]
    belly = np.clip((0.55 - y) / 0.1, 0.0, 1.0) * np.clip((y - 0.4) / 0.05, 0.0, 1.0)
    col = base * (1 - 0.55 * leg_dark) + 0.25 * belly[:, None]
    return np.clip(col, 0.0, 1.0).astype(np.float32)


def keypoint_vertices(mesh: AnimatedMesh) -> tuple[list[str], np.ndarray]:
    """Anatomical keypoints of the quadruped as rest-mesh vertex indices.

    Each keypoint is the rest surface vertex nearest to a joint's rest position plus an offset
    (e.g. feet: the sole; knees, shoulders and hips: the outer side). Returns (names (K,), vertex
    indices int64 (K,)), K = 19.
    """
    return list(KEYPOINT_NAMES), nearest_surface_vertices(mesh, JOINT_NAMES, _KEYPOINTS)


def nearest_surface_vertices(mesh: AnimatedMesh, joint_names: list[str], keypoints) -> np.ndarray:
    """Per keypoint ``(name, joint, offset)``, the rest vertex nearest to the joint's rest position plus the
    offset (metres): int64 (K,)."""
    idx = [int(np.argmin(np.linalg.norm(mesh.rest_verts - (mesh.rest_joints[joint_names.index(j)] + np.asarray(off)),
                                        axis=1))) for _, j, off in keypoints]
    return np.asarray(idx, dtype=np.int64)
