"""Skeleton scores: the learned joints against the ground truth's (distance, limb and chain coverage, limb identity)
and on their own (joints inside the body, bones that own no vertex).

* :func:`skeleton_distance`: mean distance from each ground-truth deforming joint to the nearest predicted joint
  under the sequence's alignment (:mod:`s3o_warp.evaluation.shape`), over the bounding-box diagonal, averaged over
  frames.
* :func:`limb_coverage` / :func:`chain_coverage`: is there a learned joint chain along each ground-truth limb
  (:func:`gt_limbs`) or chain.
* :func:`limb_identity`: do the fitted limbs keep their identity through the video.
* :func:`joints_inside` and :func:`empty_bones`: need no ground truth.
"""

from __future__ import annotations

import numpy as np
import torch

from s3o_warp.evaluation.shape import Similarity
from s3o_warp.ops import closest_point
from s3o_warp.skeleton.measures import assign_parts


def skeleton_distance(pred_joints: np.ndarray, gt_joints: np.ndarray, diag: np.ndarray,
                      sim: Similarity | None = None) -> dict:
    """Distance of every ground-truth joint to the nearest predicted joint, per frame.

    Args:
        pred_joints: float (T, Jp, 3) predicted joints, camera space (``sim`` is applied to them).
        gt_joints: float (T, J, 3) ground-truth deforming joints, camera space.
        diag: (T,) normalisers (the ground truth's bbox diagonal per frame).
        sim: the sequence alignment of the prediction (identity when None).

    Returns:
        ``{"distance": mean over frames of mean_j min_k |gt_j - pred_k| / diag,
        "distance_pred_to_gt": the reverse direction, "per_frame": [...], "gt_joints": J,
        "pred_joints": Jp}``.
    """
    T, J = gt_joints.shape[:2]
    Jp = pred_joints.shape[1]
    if pred_joints.shape[0] != T:
        raise ValueError(f"skeleton_distance(): {pred_joints.shape[0]} predicted frames but {T} ground-truth frames")
    if Jp == 0 or J == 0:
        return {"distance": float("nan"), "distance_pred_to_gt": float("nan"), "per_frame": [],
                "gt_joints": J, "pred_joints": Jp}
    pj = sim(pred_joints) if sim is not None else np.asarray(pred_joints, dtype=np.float64)
    d = np.linalg.norm(np.asarray(gt_joints, dtype=np.float64)[:, :, None] - pj[:, None], axis=-1)  # (T, J, Jp)
    norm = np.asarray(diag, dtype=np.float64)
    per_frame = d.min(axis=2).mean(axis=1) / norm
    rev = d.min(axis=1).mean(axis=1) / norm
    return {"distance": float(per_frame.mean()), "distance_pred_to_gt": float(rev.mean()),
            "per_frame": per_frame.tolist(), "gt_joints": int(J), "pred_joints": int(Jp)}


def joints_inside(joints: np.ndarray, verts: np.ndarray, faces: np.ndarray, device: str = "cpu") -> dict:
    """Does the skeleton sit inside the body? Signed distance of each joint to its frame's posed mesh.

    Args:
        joints: float (T, J, 3) joint positions per frame; verts: float (T, N, 3) posed vertices of
            the same frames (same space); faces: int (F, 3).
        device: where the closest-point kernel runs.

    Returns:
        ``{"fraction", "per_joint", "max_outside"}``: the fraction of (frame, joint) pairs inside the
        mesh (winding-number sign), the per-joint fraction over frames, and the largest distance of
        a joint outside (0 when none is), in the units of ``verts``.
    """
    J = np.asarray(joints, np.float64)
    V = np.asarray(verts, np.float64)
    if J.ndim != 3 or J.shape[0] != V.shape[0]:
        raise ValueError(f"joints_inside(): joints {J.shape} and verts {V.shape} must be (T, J, 3) and (T, N, 3)")
    f = torch.as_tensor(np.asarray(faces, np.int64))
    inside = np.zeros(J.shape[:2], bool)
    worst = 0.0
    for t in range(J.shape[0]):
        d, _, _ = closest_point(torch.as_tensor(V[t], dtype=torch.float32), f,
                                torch.as_tensor(J[t], dtype=torch.float32), device=device)
        d = d.cpu().numpy()
        inside[t] = d < 0
        worst = max(worst, float(d.max(initial=0.0)))
    return {"fraction": float(inside.mean()) if inside.size else float("nan"),
            "per_joint": inside.mean(0).tolist(), "max_outside": worst}


FAN_DEG = 30.0
"""A branching joint with three or more child chains that all point within this angle of one another (a hand's
fingers, a paw's toes) ends one limb instead of starting several: measured on the rigs, the robot's four fingers fan
out 18-20 degrees, every other branching of the quadrupeds and the lizard (hips, shoulders, a head's ears and nose)
44 degrees or more. Two chains are never a fan: a pair of legs can hang nearly parallel."""


def _fans(parents: np.ndarray, children: list[list[int]], joints: np.ndarray) -> dict[int, int]:
    """Fan joints (see :data:`FAN_DEG`; never the root) -> the child whose subtree reaches farthest from them."""
    def subtree(j: int) -> list[int]:
        out, stack = [j], [j]
        while stack:
            kids = children[stack.pop()]
            out += kids
            stack += kids
        return out

    fans = {}
    for j, kids in enumerate(children):
        if len(kids) < 3 or parents[j] < 0:
            continue
        far, reach = [], []
        for c in kids:
            d = joints[subtree(c)] - joints[j]
            n = np.linalg.norm(d, axis=1)
            far.append(d[int(np.argmax(n))] / max(float(n.max()), 1e-12))
            reach.append(float(n.max()))
        D = np.asarray(far)
        if float((D @ D.T).min()) >= np.cos(np.deg2rad(FAN_DEG)):
            fans[j] = kids[int(np.argmax(reach))]
    return fans


def gt_limbs(parents: np.ndarray, names: list[str] | None = None, joints: np.ndarray | None = None) -> list[dict]:
    """The limbs of a joint tree: from each leaf up to (and including) the nearest branching ancestor.

    Concretely, a limb ``{"name": "foot_fl", "joints": [8, 9, 10]}`` is the chain shoulder -> knee ->
    foot of a quadruped's front-left leg (the shoulder being where the chain meets the body). With ``joints``
    ((J, 3) positions of one pose), a fan (:data:`FAN_DEG`: a hand with its fingers) is part of the limb that
    reaches it, which goes on along its farthest-reaching finger: a biped's arm is one limb from the shoulder,
    not one per finger from the wrist.
    """
    parents = np.asarray(parents, dtype=np.int64)
    J = len(parents)
    children: list[list[int]] = [[] for _ in range(J)]
    for j, p in enumerate(parents):
        if p >= 0:
            children[p].append(j)
    if joints is not None:
        fans = _fans(parents, children, np.asarray(joints, dtype=np.float64))
        children = [[fans[j]] if j in fans else kids for j, kids in enumerate(children)]
    limbs = []
    stack = [j for j in range(J) if parents[j] < 0]
    leaves = []
    while stack:  # the leaves the kept children reach, in joint order below
        j = stack.pop()
        if children[j]:
            stack += children[j]
        else:
            leaves.append(j)
    for leaf in sorted(leaves):
        chain = [int(leaf)]
        p = int(parents[leaf])
        while p >= 0:
            chain.append(p)
            if len(children[p]) > 1 or parents[p] < 0:
                break
            p = int(parents[p])
        if len(chain) >= 2:
            nm = names[leaf] if names is not None and len(names) == J else f"joint_{leaf}"
            limbs.append({"name": nm, "joints": chain[::-1]})
    return limbs


def _point_polyline_distance(points: np.ndarray, poly: np.ndarray, along: bool = False):
    """Distance of each of ``points (M, 3)`` to the polyline ``poly (K, 3)`` (K = 1: to that point); with
    ``along`` also where the nearest point of the polyline is, as a fraction of its length from its start."""
    if len(poly) == 1:
        d = np.linalg.norm(points - poly[0], axis=-1)
        return (d, np.zeros(len(points))) if along else d
    a, b = poly[:-1], poly[1:]
    ab = b - a
    t = np.clip(np.einsum("mkd,kd->mk", points[:, None] - a[None], ab) / np.maximum((ab * ab).sum(-1), 1e-12), 0, 1)
    q = a[None] + t[..., None] * ab[None]
    dk = np.linalg.norm(points[:, None] - q, axis=-1)
    k = dk.argmin(1)
    if not along:
        return dk[np.arange(len(points)), k]
    seg = np.linalg.norm(ab, axis=-1)
    start = np.concatenate([[0.0], np.cumsum(seg)[:-1]])
    s = (start[k] + t[np.arange(len(points)), k] * seg[k]) / max(seg.sum(), 1e-12)
    return dk[np.arange(len(points)), k], s


def _distinct(pos: np.ndarray, d: np.ndarray, min_separation: float) -> np.ndarray:
    """Per joint, its distance ``d`` to the chain, or inf when a nearer joint's place along the chain ``pos``
    (a fraction of its length) is within ``min_separation`` of its own: joints at one place along a limb (a
    knot, or two side by side at its top) count once, by the nearest of them."""
    out = d.copy()
    kept: list[float] = []
    for j in np.argsort(d, kind="stable"):
        if any(abs(pos[j] - k) < min_separation for k in kept):
            out[j] = np.inf
        else:
            kept.append(float(pos[j]))
    return out


def chain_coverage(pred_joints: np.ndarray, gt_joints: np.ndarray, chain, diag: np.ndarray,
                   sim: Similarity | None = None, tol: float = 0.05, min_joints: int = 2,
                   min_separation: float = 0.0) -> dict:
    """Is there a learned joint chain along one ground-truth joint chain (``chain``: joint indices, a polyline;
    one index: a point)? The test of :func:`limb_coverage` for any chain, for example a neck between two
    branchings. Returns ``median_pred_joints`` (within ``tol`` x the bbox diagonal), ``covered`` (``min_joints``
    or more in at least half of the frames), ``tol_needed`` (covered at every ``tol`` above it; None with
    fewer than ``min_joints`` predicted joints, or distinct ones in half the frames) and ``median_span``: per frame, how much of the chain's length
    lies between the first and the last of the joints within ``tol`` (their nearest points on it), the median
    over the frames. Two joints in a knot at the hip cover a leg with a span near 0; a hip and a knee, about
    half of it. With ``min_separation`` > 0, joints whose places along the chain (nearest points, as fractions
    of its length) are closer than that to a nearer joint's count once per frame: a knot is one joint, and a
    chain must spread along the limb."""
    pj = sim(pred_joints) if sim is not None else np.asarray(pred_joints, dtype=np.float64)
    gj = np.asarray(gt_joints, dtype=np.float64)
    T = gj.shape[0]
    ds = [_point_polyline_distance(pj[t], gj[t, list(chain)], along=True) for t in range(T)]
    d = np.stack([x[0] / diag[t] for t, x in enumerate(ds)])
    pos = np.stack([x[1] for x in ds])
    if min_separation > 0:
        d = np.stack([_distinct(pos[t], d[t], min_separation) for t in range(T)])
    near = d < tol
    counts = near.sum(1)
    span = np.where(near.any(1), np.where(near, pos, -np.inf).max(1) - np.where(near, pos, np.inf).min(1), 0.0)
    # the min_joints-th nearest joint per frame; covered iff it is < tol in ceil(T / 2) frames or more
    kth = np.sort(d, axis=1)[:, min_joints - 1] if d.shape[1] >= min_joints else None
    need = None if kth is None else float(np.sort(kth)[int(np.ceil(T / 2)) - 1])
    return {"median_pred_joints": float(np.median(counts)), "covered": bool((counts >= min_joints).mean() >= 0.5),
            "tol_needed": need if need is None or np.isfinite(need) else None,
            "median_span": float(np.median(span))}


def limb_coverage(pred_joints: np.ndarray, gt_joints: np.ndarray, gt_parents: np.ndarray, diag: np.ndarray,
                  sim: Similarity | None = None, names: list[str] | None = None, tol: float = 0.05,
                  min_joints: int = 2, branch: bool = True, min_separation: float = 0.0,
                  tips: dict[int, np.ndarray] | None = None) -> dict:
    """Does every ground-truth limb have a learned joint chain along it?

    A limb (see :func:`gt_limbs`, with the first frame's joints telling a hand from a branching) counts as covered when, in at least half of the frames, ``min_joints``
    or more predicted joints lie within ``tol`` x the bbox diagonal of the limb's polyline (after the
    sequence alignment ``sim``). Returns per-limb median counts, ``tol_needed`` (the limb is covered at
    every ``tol`` above it; None with fewer than ``min_joints`` predicted joints) and the covered fraction.
    ``branch=False`` leaves the branching ancestor out of the polyline (the limb's own joints: a tail from its
    base, not from the pelvis), so a joint where the limb meets the body, or a neighbouring limb's, does not
    count for it. ``min_separation`` > 0: joints closer than that along the chain (a fraction of its length) to
    a nearer one count once (:func:`chain_coverage`), so a knot at the top of a leg does not pass for a chain.
    ``tips`` (end joint index -> (T, 3) points): a limb whose end joint has one goes on to it, so its last bone
    is part of it (a joint's position is where its bone starts: a horse's lower-leg joint is its knee, and a
    third of the leg lies between it and the hoof).
    """
    gj = np.asarray(gt_joints, dtype=np.float64)
    J = gj.shape[1]
    out = []
    for limb in gt_limbs(gt_parents, names, gj[0]):
        chain = limb["joints"] if branch else limb["joints"][1:]
        tip = (tips or {}).get(limb["joints"][-1])
        points, chain = (gj, chain) if tip is None else (  # the end joint's tip as one more point of the polyline
            np.concatenate([gj, np.asarray(tip, np.float64)[:, None]], 1), list(chain) + [J])
        c = chain_coverage(pred_joints, points, chain, diag, sim, tol, min_joints, min_separation)
        out.append({"limb": limb["name"], "gt_joints": len(limb["joints"]), "to_tip": tip is not None, **c})
    n = len(out)
    return {"limbs": out, "covered": sum(o["covered"] for o in out), "total": n, "tol": tol, "min_joints": min_joints,
            "branch": branch, "min_separation": min_separation, "to_tip": any(o["to_tip"] for o in out)}


def empty_bones(weights: np.ndarray) -> dict:
    """Bones that are the largest weight of no vertex (``weights`` ``(N, B)``): they move nothing, and their
    joints fall back to far-apart borders. Returns ``count`` (B) and ``empty`` (their indices)."""
    W = np.asarray(weights)
    if W.ndim != 2 or W.shape[1] == 0:
        raise ValueError(f"empty_bones(): weights must have shape (N, B) with B >= 1, got {W.shape}")
    owned = np.bincount(assign_parts(W), minlength=W.shape[1])
    return {"count": int(W.shape[1]), "empty": np.flatnonzero(owned == 0).tolist()}


def limb_identity(pred_verts: np.ndarray, weights: np.ndarray, gt_joints: np.ndarray, gt_parents: np.ndarray,
                  sim: Similarity | None = None, names: list[str] | None = None, k: int = 5) -> dict:
    """Do the fitted limbs keep their identity through the video, or swap places (legs that bounce off
    each other where the real ones cross)?

    Per ground-truth limb (see :func:`gt_limbs`) and frame, the ``k`` predicted vertices nearest to the
    limb's tip joint (after the sequence alignment ``sim``) vote with their dominant bone. The limb's bone
    is the most frequent winner over the frames. A frame is *swapped* when the winner is another limb's
    bone and not its own. Returns per limb its bone, the fraction of frames it wins (``kept``), the
    ``swapped`` fraction and ``shared`` (another limb has the same bone: the fit gave both one part), and
    ``mean_swapped`` over the limbs.
    """
    pv = sim(pred_verts) if sim is not None else np.asarray(pred_verts, dtype=np.float64)  # (T, N, 3)
    T = pv.shape[0]
    gj = np.asarray(gt_joints, dtype=np.float64)
    dom = np.asarray(weights).argmax(1)
    k = max(1, min(int(k), pv.shape[1]))
    limbs = gt_limbs(gt_parents, names, gj[0])
    wins = np.empty((len(limbs), T), dtype=np.int64)
    for i, limb in enumerate(limbs):
        tip = gj[:, limb["joints"][-1]]  # (T, 3)
        near = np.argpartition(np.linalg.norm(pv - tip[:, None], axis=-1), k - 1, axis=1)[:, :k]
        wins[i] = [np.bincount(dom[n]).argmax() for n in near]
    own = [int(np.bincount(w).argmax()) for w in wins]
    out = []
    for i, limb in enumerate(limbs):
        others = {b for j, b in enumerate(own) if j != i and b != own[i]}
        out.append({"limb": limb["name"], "bone": own[i], "kept": float((wins[i] == own[i]).mean()),
                    "swapped": float(np.isin(wins[i], list(others)).mean()) if others else 0.0,
                    "shared": own.count(own[i]) > 1})
    return {"limbs": out, "mean_swapped": float(np.mean([o["swapped"] for o in out])) if out else 0.0, "k": k}

