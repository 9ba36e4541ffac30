"""What the M-step measures (paper 3.4), as pure functions: the semi-rigid parts ``I_b`` of eq. 5 and their
extents, the kinematic tree over the joints, each bone's image motion from the optical flow (eq. 4), the motion
similarity of two bones (eq. 8) and how much of two parts' relative motion a fit leaves unexplained (not in the
paper), bone lengths over the frames and their variation (eq. 6, corrected), and the skeleton in the paper's
notation (``skeleton.json``); the bottom of :mod:`s3o_warp.skeleton`, below the edits
(:mod:`~s3o_warp.skeleton.edit`, :mod:`~s3o_warp.skeleton.joints`) and their schedule
(:mod:`~s3o_warp.skeleton.mstep`). Notation (paper Table 4): ``X^0 = M_c`` canonical vertices ``(N, 3)`` (object
frame), ``W`` skinning weights ``(N, B)``, ``I_b`` the vertices whose largest weight is bone b, ``F^{B,t}``
``(B, 2)`` bone motion between frames t and t+1 (crop pixels), ``V^t`` ``(N,)`` vertex visibility at frame t.
Every threshold is a keyword argument whose default is the paper's value where it gives one; inputs may be numpy
arrays or torch tensors.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np
import torch
from scipy.spatial import ConvexHull
from scipy.spatial.distance import pdist

from s3o_warp.geometry import project
from s3o_warp.geometry import to_numpy as _np

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------------
# array helpers
# ---------------------------------------------------------------------------------------------------


def _check(name: str, arg: str, a: np.ndarray, shape: tuple) -> None:
    """Raise a ValueError naming ``name()`` and ``arg`` unless ``a`` has ``shape`` (None: any size)."""
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        want = "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name}(): {arg} must have shape {want}, got {tuple(a.shape)}")


def _bones_in(name: str, verts, weights, centers=None, precisions=None, parents=None):
    """The checked ``X`` ``(N, 3)``, ``W`` ``(N, B)`` and those of ``C`` ``(B, 3)``, ``Q`` ``(B, 3, 3)`` and
    ``parents`` ``(B,)`` that are given, in that order, as numpy arrays."""
    X = _np(verts)
    _check(name, "verts", X, (None, 3))
    W = _np(weights)
    _check(name, "weights", W, (X.shape[0], None))
    B = W.shape[1]
    out = [X, W]
    if centers is not None:
        C = _np(centers)
        _check(name, "centers", C, (B, 3))
        out.append(C)
    if precisions is not None:
        Q = _np(precisions)
        _check(name, "precisions", Q, (B, 3, 3))
        out.append(Q)
    if parents is not None:
        P = _np(parents, np.int64)
        _check(name, "parents", P, (B,))
        if ((P < -1) | (P >= B)).any():
            raise ValueError(f"{name}(): parents entries must be -1 (a root) or a bone index in [0, {B})")
        out.append(P)
    return out


# ---------------------------------------------------------------------------------------------------
# semi-rigid parts (eq. 5)
# ---------------------------------------------------------------------------------------------------


def assign_parts(weights) -> np.ndarray:
    """``(N,)`` int64 argmax bone of each vertex: vertex n belongs to the part ``I_b`` of ``b = argmax_b W[n, b]``."""
    return np.argmax(_np(weights), axis=1).astype(np.int64)


def part_extents(verts, weights) -> np.ndarray:
    """``(B,)`` maximum internal distance of each part ``I_b`` (diameter of its argmax vertices; 0 if < 2).

    The diameter is exact: the farthest pair of a point set lies on its convex hull (scipy's Qhull,
    joggled for flat sets), so only hull vertices are compared.
    """
    X, W = _bones_in("part_extents", verts, weights)
    lab = assign_parts(W)
    return np.array([_diameter(X[lab == b]) for b in range(W.shape[1])], np.float64)


def _diameter(p: np.ndarray) -> float:
    """Largest pairwise distance of a point set (0 for fewer than 2 points)."""
    if len(p) < 2:
        return 0.0
    if len(p) > 64:
        try:
            p = p[ConvexHull(p, qhull_options="QJ").vertices]
        except Exception:  # noqa: BLE001 - Qhull fails on degenerate sets; the pairwise check is exact anyway
            pass
    return float(pdist(p).max())


def size_of(verts) -> float:
    """The bbox diagonal of ``(N, 3)`` canonical vertices: the unit of the M-step's relative lengths
    (``s3o_warp.skeleton.mstep.JOINT_DEPTH``, ``MIN_BONE_LENGTH``)."""
    X = _np(verts)
    return float(np.linalg.norm(X.max(0) - X.min(0)))


# ---------------------------------------------------------------------------------------------------
# kinematic tree
# ---------------------------------------------------------------------------------------------------


def children_of(parents) -> list[list[int]]:
    """Children lists of a kinematic tree given as ``parents`` ``(B,)`` (-1 = root)."""
    P = _np(parents, np.int64)
    ch: list[list[int]] = [[] for _ in range(len(P))]
    for b, p in enumerate(P):
        if p >= 0:
            ch[int(p)].append(b)
    return ch


def tree_joints(parents) -> np.ndarray:
    """``(J, 2)`` int64 joints of a kinematic tree: one ``(parent, child)`` pair per non-root bone, by child index."""
    P = _np(parents, np.int64)
    kids = np.flatnonzero(P >= 0)
    return np.stack([P[kids], kids], 1).astype(np.int64).reshape(-1, 2)


def kinematic_tree(num_bones: int, joints, root: int | None = None, weights=None, centers=None) -> np.ndarray:
    """A spanning tree of the joint graph: ``(B,)`` int64 parents, -1 at the root.

    Breadth-first from the root bone (``root``, else the bone with the most argmax vertices when
    ``weights`` is given, else bone 0); neighbours are visited in index order. Bones the walk cannot
    reach (no joint path to the root) are attached one at a time: the unreached bone whose centre is
    nearest a reached bone's centre hangs from that bone (bone 0 order without ``centers``), then the
    walk continues through its own joints. So the result is always a single tree.

    Args:
        num_bones: B.
        joints: ``(J, 2)`` bone pairs.
        root: optional root bone.
        weights: optional ``(N, B)`` W for choosing the root.
        centers: optional ``(B, 3)`` centres for attaching unconnected bones.
    """
    B = int(num_bones)
    if B < 1:
        raise ValueError(f"kinematic_tree(): num_bones must be >= 1, got {num_bones}")
    Jp = _np(joints, np.int64).reshape(-1, 2)
    if ((Jp < 0) | (Jp >= B)).any():
        raise ValueError(f"kinematic_tree(): joints must index bones in [0, {B})")
    if root is None:
        root = int(np.argmax(np.bincount(assign_parts(weights), minlength=B))) if weights is not None else 0
    if not 0 <= root < B:
        raise ValueError(f"kinematic_tree(): root must be in [0, {B}), got {root}")
    nb: list[set[int]] = [set() for _ in range(B)]
    for a, b in Jp:
        if a != b:
            nb[int(a)].add(int(b))
            nb[int(b)].add(int(a))
    C = None if centers is None else _np(centers)
    parents = np.full(B, -2, np.int64)
    parents[root] = -1

    def walk(start: int) -> None:
        q = deque([start])
        while q:
            a = q.popleft()
            for b in sorted(nb[a]):
                if parents[b] == -2:
                    parents[b] = a
                    q.append(b)

    walk(root)
    while (parents == -2).any():
        out = np.flatnonzero(parents == -2)
        inn = np.flatnonzero(parents != -2)
        if C is None:
            b, a = int(out[0]), int(root)
        else:
            d = np.linalg.norm(C[out][:, None] - C[inn][None], axis=-1)
            i, k = np.unravel_index(np.argmin(d), d.shape)
            b, a = int(out[i]), int(inn[k])
        parents[b] = a
        log.info("kinematic_tree: bone %d has no joint path to the root; attached to bone %d", b, a)
        walk(b)
    return parents


# ---------------------------------------------------------------------------------------------------
# bone motion from optical flow (eq. 4) and motion similarity (eq. 8)
# ---------------------------------------------------------------------------------------------------


def bone_flow(
    verts_cam: torch.Tensor,
    K: torch.Tensor,
    flow: torch.Tensor,
    visible: torch.Tensor,
    weights: torch.Tensor,
    conf: torch.Tensor | None = None,
    min_visible: float = 0.1,
    min_mass: float = 3.0,
    predicted: torch.Tensor | None = None,
):
    """Per-bone image motion ``F^{B,t}`` from the observed flow, eq. 4, normalised.

    For each pair (t, t+1): project frame t's vertices with ``K[t]``, sample ``flow[t]`` bilinearly
    at the projections (OpenCV pixel centres: pixel (c, r) is at (c, r), so sampling at integer
    coordinates returns that pixel's flow exactly), keep the visible vertices that land inside the
    image (``v_n = V_n^t``, times the sampled ``conf`` if given) and blend per bone:
    ``F_b^{B,t} = sum_n W[n,b] v_n F_n^{S,t} / sum_n W[n,b] v_n``. The paper's eq. 4 is unnormalised,
    which makes a barely visible bone's vector short and its cosine noisy; normalising by the visible
    weight mass gives the mean flow of what is seen, and ``valid`` drops what is barely seen.

    Args:
        verts_cam: ``(T, N, 3)`` posed vertices in the camera frame (OpenCV, +z forward).
        K: ``(T, 3, 3)`` intrinsics in the pixels of the image ``flow`` lives on (the crop).
        flow: ``(T-1, H, W, 2)`` forward flow t -> t+1 as (dx, dy) in pixels.
        visible: ``(T, N)`` bool vertex visibility (``s3o_warp.ops.vertex_visibility``).
        weights: ``(N, B)`` skinning weights W.
        conf: optional ``(T-1, H, W)`` flow confidence in [0, 1] (forward-backward consistency).
        min_visible: a bone is valid at t when its visible weight mass is at least this fraction of
            its total mass ``sum_n W[n, b]``...
        min_mass: ...and at least this many vertices' worth of weight.
        predicted: optional ``(T-1, N, 2)`` per-vertex motion of the fitted model in the same pixels as the
            returned flow (``s3o_warp.motion.losses.vertex_flow_crop`` for the crop flow), blended with the same
            visibility and weights as the observed flow.

    Returns:
        ``F_B`` ``(T-1, B, 2)`` float32 bone flow in pixels (0 where not valid) and ``valid``
        ``(T-1, B)`` bool. Concretely, ``valid[t, b]`` is False when bone b is barely visible in frame t.
        With ``predicted`` also ``G_B`` ``(T-1, B, 2)``, its blend (0 where not valid).
    """
    name = "bone_flow"
    if not (verts_cam.dim() == 3 and verts_cam.shape[-1] == 3):
        raise ValueError(f"{name}(): verts_cam must have shape (T, N, 3), got {tuple(verts_cam.shape)}")
    T, N = verts_cam.shape[:2]
    if T < 2:
        raise ValueError(f"{name}(): need at least 2 frames, got {T}")
    if tuple(K.shape) != (T, 3, 3):
        raise ValueError(f"{name}(): K must have shape ({T}, 3, 3), got {tuple(K.shape)}")
    if flow.dim() != 4 or flow.shape[0] != T - 1 or flow.shape[-1] != 2:
        raise ValueError(f"{name}(): flow must have shape ({T - 1}, H, W, 2), got {tuple(flow.shape)}")
    if tuple(visible.shape) != (T, N):
        raise ValueError(f"{name}(): visible must have shape ({T}, {N}), got {tuple(visible.shape)}")
    if weights.dim() != 2 or weights.shape[0] != N:
        raise ValueError(f"{name}(): weights must have shape ({N}, B), got {tuple(weights.shape)}")
    H, Wd = flow.shape[1:3]
    if conf is not None and tuple(conf.shape) != (T - 1, H, Wd):
        raise ValueError(f"{name}(): conf must have shape ({T - 1}, {H}, {Wd}), got {tuple(conf.shape)}")
    if predicted is not None and tuple(predicted.shape) != (T - 1, N, 2):
        raise ValueError(f"{name}(): predicted must have shape ({T - 1}, {N}, 2), got {tuple(predicted.shape)}")
    with torch.no_grad():
        dev = verts_cam.device
        v = verts_cam[:-1].float()
        uv = project(v, K[:-1].to(dev).float())  # (T-1, N, 2)
        inside = (
            (v[..., 2] > 0)
            & (uv[..., 0] >= -0.5) & (uv[..., 0] <= Wd - 0.5)
            & (uv[..., 1] >= -0.5) & (uv[..., 1] <= H - 0.5)
        )
        # align_corners=True: -1 and +1 are the centres of the first and last pixels (OpenCV centres)
        g = torch.stack([2 * uv[..., 0] / max(Wd - 1, 1) - 1, 2 * uv[..., 1] / max(H - 1, 1) - 1], -1)[:, None]
        img = flow.to(dev).float().permute(0, 3, 1, 2)
        if conf is not None:
            img = torch.cat([img, conf.to(dev).float()[:, None]], 1)
        s = torch.nn.functional.grid_sample(img, g, mode="bilinear", padding_mode="border", align_corners=True)
        s = s[:, :, 0].permute(0, 2, 1)  # (T-1, N, C)
        f = s[..., :2]
        vis = (visible[:-1].to(dev).bool() & inside).float()
        if conf is not None:
            vis = vis * s[..., 2].clamp(0, 1)
        Wf = weights.to(dev).float()
        mass = vis @ Wf  # (T-1, B)
        num = torch.einsum("tnc,nb->tbc", vis[..., None] * f, Wf)
        total = Wf.sum(0)
        valid = (mass >= min_visible * total) & (mass >= min_mass) & (mass > 0)
        F = torch.where(valid[..., None], num / mass.clamp_min(1e-12)[..., None], torch.zeros_like(num))
        if predicted is None:
            return F, valid
        g = torch.einsum("tnc,nb->tbc", vis[..., None] * predicted.to(dev).float(), Wf)
        G = torch.where(valid[..., None], g / mass.clamp_min(1e-12)[..., None], torch.zeros_like(g))
    return F, valid, G


def motion_similarity(F_B: torch.Tensor, valid: torch.Tensor, min_flow: float = 0.5,
                      min_frames: int = 2, return_frames: bool = False):
    """Motion similarity of every bone pair, eq. 8: ``min_f S(F_b^f, F_b'^f)`` over frames both see.

    ``S`` is the cosine similarity, made safe for static frames: with ``m = min_flow`` (pixels),
    ``S_m(a, b) = a.b / (max(|a|, m) max(|b|, m))``. It equals the cosine when both vectors are
    longer than m; a frame where BOTH are shorter than m says nothing about direction and is skipped;
    where only one is short, S_m shrinks smoothly towards 0 (one part moves, the other does not:
    not moving together). Pairs with fewer than ``min_frames`` usable frames get ``-inf`` (never
    merged). The diagonal is 1.

    Args:
        F_B: ``(T-1, B, 2)`` bone flow (:func:`bone_flow`), pixels.
        valid: ``(T-1, B)`` bool.
        min_flow: m, the magnitude (pixels) below which a bone counts as static in a frame.
        min_frames: fewest common usable frames for a finite similarity.
        return_frames: also return how many usable frames each pair has.

    Returns:
        ``(B, B)`` float32 symmetric similarities in [-1, 1] or -inf; with ``return_frames`` also the
        ``(B, B)`` int64 counts of usable frames (the diagonal: the frames a bone is seen moving).
    """
    if F_B.dim() != 3 or F_B.shape[-1] != 2:
        raise ValueError(f"motion_similarity(): F_B must have shape (T-1, B, 2), got {tuple(F_B.shape)}")
    if tuple(valid.shape) != tuple(F_B.shape[:2]):
        raise ValueError(f"motion_similarity(): valid must have shape {tuple(F_B.shape[:2])}, got {tuple(valid.shape)}")
    min_flow = max(float(min_flow), 1e-9)
    with torch.no_grad():
        F = F_B.float()
        mag = F.norm(dim=-1)  # (T', B)
        den = mag.clamp_min(min_flow)
        S = torch.einsum("tbc,tdc->tbd", F, F) / (den[:, :, None] * den[:, None, :])
        moving = mag >= min_flow
        use = valid[:, :, None] & valid[:, None, :] & (moving[:, :, None] | moving[:, None, :])
        out = torch.where(use, S, torch.full_like(S, float("inf"))).min(0).values
        out = torch.where(use.sum(0) >= min_frames, out, torch.full_like(out, float("-inf")))
        out.fill_diagonal_(1.0)
    return (out, use.sum(0)) if return_frames else out


def unexplained_motion(F_B: torch.Tensor, G_B: torch.Tensor, valid: torch.Tensor, pairs, min_flow: float = 0.5,
                       min_frames: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """How much of the relative image motion of two parts the fitted motion leaves unexplained (not in the paper).

    For each pair ``(p, d)`` of columns (the two halves of one bone's part, :func:`s3o_warp.skeleton.joints.bone_halves`)
    and each frame pair both are seen in: the observed relative motion ``o = F_d - F_p`` and the fitted one
    ``g = G_d - G_p``, and ``r = |o - g| / max(|o|, |g|)`` (0 where both are under ``min_flow``). The result is the median of r over those
    frames: about 0 when the fit moves the halves as the video does (a rigid part fitted well: its far half
    turning about the near one is reproduced), towards 0.5 and above when the video's halves move relative to
    each other in a way one rigid bone cannot follow (a knee inside the part). Pairs seen in fewer than
    ``min_frames`` frames get NaN.

    Args:
        F_B, G_B: ``(T-1, B, 2)`` observed and fitted bone flow (:func:`bone_flow` with ``predicted``).
        valid: ``(T-1, B)`` bool.
        pairs: ``(K, 2)`` column pairs (near half, far half).
        min_flow: pixels; relative motions below it in both count as agreement.
        min_frames: fewest frames for a finite result.

    Returns:
        ``(K,)`` float64 medians (NaN where too few frames) and ``(K,)`` int64 frame counts.
    """
    P = _np(pairs, np.int64).reshape(-1, 2)
    if F_B.dim() != 3 or tuple(G_B.shape) != tuple(F_B.shape) or tuple(valid.shape) != tuple(F_B.shape[:2]):
        raise ValueError(f"unexplained_motion(): need F_B and G_B (T-1, B, 2) and valid (T-1, B), got "
                         f"{tuple(F_B.shape)}, {tuple(G_B.shape)}, {tuple(valid.shape)}")
    if len(P) and (P.min() < 0 or P.max() >= F_B.shape[1]):
        raise ValueError(f"unexplained_motion(): pairs must index the {F_B.shape[1]} columns, got {P.tolist()}")
    F = F_B.detach().cpu().double().numpy()
    G = G_B.detach().cpu().double().numpy()
    ok = valid.detach().cpu().numpy().astype(bool)
    out, frames = np.full(len(P), np.nan), np.zeros(len(P), np.int64)
    for k, (a, b) in enumerate(P):
        use = ok[:, a] & ok[:, b]
        frames[k] = int(use.sum())
        if frames[k] < max(int(min_frames), 1):
            continue
        o = F[use, b] - F[use, a]
        g = G[use, b] - G[use, a]
        big = np.maximum(np.linalg.norm(o, axis=1), np.linalg.norm(g, axis=1))
        r = np.linalg.norm(o - g, axis=1) / np.maximum(big, 1e-12)
        out[k] = float(np.median(np.where(big >= float(min_flow), r, 0.0)))
    return out, frames


# ---------------------------------------------------------------------------------------------------
# bone lengths and their variation (eq. 6, corrected)
# ---------------------------------------------------------------------------------------------------


def bone_lengths(endpoints, verts) -> np.ndarray:
    """Bone lengths ``|E[b,1] X - E[b,0] X|``: ``(B,)`` for ``(N, 3)`` verts, ``(T, B)`` for posed ``(T, N, 3)``.

    Per frame, the length of bone b is the distance between its two endpoints
    (:func:`s3o_warp.skeleton.joints.bone_endpoints`) carried by the posed vertices; a joint's vertex set moves
    with the blend of both its bones, so a bone whose region bends or stretches changes length, a rigidly moving
    one does not.
    """
    E = _np(endpoints)
    X = _np(verts)
    if E.ndim != 3 or E.shape[1] != 2 or X.shape[-1] != 3 or X.shape[-2] != E.shape[2]:
        raise ValueError(f"bone_lengths(): need endpoints (B, 2, N) and verts (..., N, 3), got {E.shape}, {X.shape}")
    B, _, N = E.shape
    ends = np.matmul(E.reshape(2 * B, N), X).reshape(X.shape[:-2] + (B, 2, 3))
    return np.linalg.norm(ends[..., 1, :] - ends[..., 0, :], axis=-1)


def bone_lengths_per_frame(endpoints, verts_posed) -> np.ndarray:
    """``(T, B)`` lengths of every bone in every frame from posed vertices ``(T, N, 3)`` (any rigid frame)."""
    X = _np(verts_posed)
    if X.ndim != 3:
        raise ValueError(f"bone_lengths_per_frame(): verts_posed must have shape (T, N, 3), got {X.shape}")
    return bone_lengths(endpoints, X)


def create_joints(lengths, t_d: float = 0.25, min_length: float = 0.0) -> np.ndarray:
    """Which bones get a new joint, eq. 6 corrected: ``(max_f L_b^f - min_f L_b^f) / median_f L_b^f > t_d``.

    The paper compares two different bones (a typo); the intent is one bone's length range over the
    frames. The range is taken relative to the bone's median length because a monocular
    reconstruction's units are arbitrary (an absolute t_d would depend on the scene scale). Bones
    of median length 0 never qualify. Apply the result with :func:`s3o_warp.skeleton.joints.split_at_joints`.

    Calibration: our bones rotate about their own centres, so the blend region at a joint drifts
    towards the rotating neighbour's centre. Measured on a rigid 3-bone capsule (16k vertices,
    bones 1 unit long) whose end bones turn by 35 and 69 degrees, the middle bone's relative length
    range is 0.19-0.21 with no stretch at all. The default t_d = 0.25 sits above that; lower values
    also split rigid bones between strongly bending neighbours.

    Because the test is relative, a short bone at a strongly bending joint qualifies again and again and
    its halves too; ``min_length`` (not in the paper) stops that: a bone is only split when both halves
    would be at least ``min_length`` long (median length >= 2 x min_length).

    Args:
        lengths: ``(T, B)`` per-frame bone lengths (:func:`bone_lengths_per_frame`).
        t_d: relative length-variation threshold (not given in the paper; see Calibration).
        min_length: shortest half a split may leave, in the units of ``lengths`` (0 = no limit).

    Returns:
        ``(B,)`` bool.
    """
    L = _np(lengths)
    if L.ndim != 2:
        raise ValueError(f"create_joints(): lengths must have shape (T, B), got {L.shape}")
    med = np.median(L, axis=0)
    rng = L.max(0) - L.min(0)
    return (med > 1e-12) & (med >= 2.0 * min_length) & (rng > t_d * np.maximum(med, 1e-12))


# ---------------------------------------------------------------------------------------------------
# skeleton.json
# ---------------------------------------------------------------------------------------------------


def skeleton_json(centers, precisions, lengths, parents, joints, joint_pos, root: int | None = None) -> dict:
    """The skeleton in the paper's notation, ready for ``json.dumps``.

    ``B`` ``(B, 13)``: per bone centre (3), precision row-major (9), length (1); ``J`` ``(J, 5)``: per
    joint the two bone indices (2) and the position (3); plus the same as named fields and the
    kinematic tree (``root`` and ``parents``, -1 for a root). Object frame, object units.

    Args:
        centers: ``(B, 3)``. precisions: ``(B, 3, 3)``. lengths: ``(B,)``. parents: ``(B,)``.
        joints: ``(J, 2)`` bone pairs. joint_pos: ``(J, 3)``.
        root: the root bone (default: the first bone whose parent is -1).
    """
    C = _np(centers)
    B = len(C)
    _check("skeleton_json", "centers", C, (None, 3))
    Q = _np(precisions)
    _check("skeleton_json", "precisions", Q, (B, 3, 3))
    L = _np(lengths)
    _check("skeleton_json", "lengths", L, (B,))
    P = _np(parents, np.int64)
    _check("skeleton_json", "parents", P, (B,))
    Jp = _np(joints, np.int64).reshape(-1, 2)
    Jx = _np(joint_pos).reshape(-1, 3)
    if len(Jp) != len(Jx):
        raise ValueError(f"skeleton_json(): {len(Jp)} joints but {len(Jx)} joint positions")
    if root is None:
        roots = np.flatnonzero(P < 0)
        root = int(roots[0]) if len(roots) else 0
    Bm = np.concatenate([C, Q.reshape(B, 9), L[:, None]], 1)
    Jm = np.concatenate([Jp.astype(np.float64), Jx], 1)
    return {
        "notation": "B: centre(3) precision(9, row-major) length(1); J: bone i, bone j, position(3); object frame",
        "B": Bm.tolist(),
        "J": Jm.tolist(),
        "bones": [
            {"centre": C[b].tolist(), "precision": Q[b].tolist(), "length": float(L[b]), "parent": int(P[b])}
            for b in range(B)
        ],
        "joints": [{"bones": [int(a), int(b)], "position": x.tolist()} for (a, b), x in zip(Jp, Jx)],
        "root": int(root),
        "parents": P.tolist(),
    }


__all__ = [
    "assign_parts",
    "bone_flow",
    "bone_lengths",
    "bone_lengths_per_frame",
    "children_of",
    "create_joints",
    "kinematic_tree",
    "motion_similarity",
    "part_extents",
    "size_of",
    "skeleton_json",
    "tree_joints",
    "unexplained_motion",
]
