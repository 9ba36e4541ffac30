"""Skeleton edits of the M-step (paper 3.4) as pure functions: bone shifting (eq. 5) and fitting bones to
labelled parts, skeleton growth at stretched end parts, the one skeleton upsampling of Algorithm 1 (epoch e1),
bone merging (eqs. 8-9, log-space weights) and the pruning of short or empty bones (not in the paper); joint
creation (eqs. 6-7) is in :mod:`s3o_warp.skeleton.joints`. Each edit takes the canonical vertices ``X^0 = M_c``
``(N, 3)``, the skinning weights ``W`` ``(N, B)`` and the bones (centres ``C`` ``(B, 3)``, precisions ``Q``
``(B, 3, 3)``, kinematic tree ``parents`` ``(B,)``, -1 for a root), all in the object frame, and returns a
:class:`SkeletonEdit`: the new bones and, for each, the old bones (with weights) whose motion it inherits, which
:func:`s3o_warp.skeleton.remap.apply_edit` applies to the model without a jump in the posed mesh. A new bone's
precision comes from its vertices' covariance, ``Q = sharpness * (Sigma + eps tr(Sigma)/3 I)^-1``: with the
default sharpness 2/3, points on the surface of an ellipsoid with radii r (surface variance r^2/3 per axis) get
``Q = 2 / r^2``, the precision the coarse initialisation gives the same ellipsoid (``precision_sharpness = 2``).
Inputs may be numpy arrays or torch tensors; outputs are float64/int64 numpy arrays.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from s3o_warp.geometry import axis_angle_to_matrix, matrix_to_quat
from s3o_warp.skeleton.measures import (
    _bones_in,
    _check,
    _diameter,
    _np,
    assign_parts,
    children_of,
    part_extents,
)

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------------
# precisions
# ---------------------------------------------------------------------------------------------------


DEFAULT_SHARPNESS = 2.0 / 3.0
"""Precision of a new bone = sharpness x inverse covariance of its vertices (see module docstring)."""


def precision_from_points(points, sharpness: float = DEFAULT_SHARPNESS, eps: float = 1e-2,
                          fallback: np.ndarray | None = None) -> np.ndarray:
    """Gaussian precision ``Q (3, 3)`` of a vertex set: ``sharpness * (Sigma + eps tr(Sigma)/3 I)^-1``.

    Args:
        points: ``(n, 3)`` vertices (object frame).
        sharpness: scale of the precision (see the module docstring for the default's meaning).
        eps: relative ridge that keeps flat or thin sets invertible.
        fallback: ``(3, 3)`` precision returned for fewer than 4 points (default: isotropic from their spread, or I).
    """
    p = _np(points).reshape(-1, 3)
    if len(p) < 4:
        if fallback is not None:
            return _np(fallback).copy()
        var = float(((p - p.mean(0)) ** 2).sum(1).mean() / 3) if len(p) > 1 else 0.0
        return np.eye(3) * (sharpness / var if var > 1e-12 else 1.0)
    cov = np.cov(p.T, bias=True)
    cov = cov + eps * max(np.trace(cov) / 3, 1e-12) * np.eye(3)
    Q = sharpness * np.linalg.inv(cov)
    return 0.5 * (Q + Q.T)


def precision_to_quat_scales(precisions) -> tuple[np.ndarray, np.ndarray]:
    """Split precisions ``Q = V^T diag(exp s) V`` ``(B, 3, 3)`` into the model's parameters.

    Returns:
        ``quats`` ``(B, 4)`` (w, x, y, z) of the orientation V (rows = the Gaussian's axes) and
        ``log_scales`` ``(B, 3)`` = s, both float64. Eigenvalues are clamped at 1e-12.
    """
    Q = _np(precisions).reshape(-1, 3, 3)
    lam, U = np.linalg.eigh(0.5 * (Q + np.transpose(Q, (0, 2, 1))))
    V = np.transpose(U, (0, 2, 1)).copy()
    V[np.linalg.det(V) < 0, 2] *= -1  # proper rotations (flipping an axis leaves Q unchanged)
    quats = matrix_to_quat(torch.as_tensor(V)).numpy()
    return quats, np.log(np.maximum(lam, 1e-12))


# ---------------------------------------------------------------------------------------------------
# the edit record
# ---------------------------------------------------------------------------------------------------


@dataclass
class SkeletonEdit:
    """A new bone list and where each new bone's motion comes from.

    Attributes:
        centers: ``(B', 3)`` float64 Gaussian centres C (object frame).
        precisions: ``(B', 3, 3)`` float64 precisions Q.
        parents: ``(B',)`` int64 kinematic tree, -1 for a root.
        sources: one list per new bone of ``(old bone, weight)`` pairs, weights summing to 1.
            Concretely, ``sources[j] == [(i, 1.0)]`` means new bone j moves exactly like old bone i.
        kept: ``(B',)`` bool, True where the new bone IS its single source unchanged (same centre and
            precision), so its parameters and optimiser state can be copied bit for bit.
        extents: ``(B',)`` float64 reference part extents for the growth test (None if not tracked).
        joints: ``(K, 2)`` int64 bone pairs of joints the edit created, with ``joint_positions`` ``(K, 3)``.
    """

    centers: np.ndarray
    precisions: np.ndarray
    parents: np.ndarray
    sources: list
    kept: np.ndarray
    extents: np.ndarray | None = None
    joints: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    joint_positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def num_bones(self) -> int:
        return len(self.centers)

    @property
    def changed(self) -> bool:
        """False when the edit is the identity (every bone kept in place: nothing to remap)."""
        return not (bool(self.kept.all()) and all(s == [(j, 1.0)] for j, s in enumerate(self.sources)))

    def old_to_new(self, num_old: int) -> list[list[int]]:
        """For each old bone, the new bones that inherit (part of) its motion."""
        out: list[list[int]] = [[] for _ in range(num_old)]
        for j, src in enumerate(self.sources):
            for i, _w in src:
                out[i].append(j)
        return out


def _identity_edit(C, Q, P, extents=None) -> SkeletonEdit:
    B = len(C)
    return SkeletonEdit(C.copy(), Q.copy(), P.copy(), [[(b, 1.0)] for b in range(B)], np.ones(B, bool),
                        None if extents is None else _np(extents).copy())


# ---------------------------------------------------------------------------------------------------
# bone shifting (eq. 5)
# ---------------------------------------------------------------------------------------------------


def shift_bones(verts, weights, centers) -> np.ndarray:
    """Bone shifting, eq. 5: ``C_b <- (1/|I_b|) sum_{n in I_b} X_n^0``, the centroid of b's argmax part.

    Bones that are the argmax of no vertex keep their centre. Apply the result with
    :func:`s3o_warp.skeleton.remap.remap_bones` (identity ``sources``), which re-pivots each bone's per-frame
    translation so the posed mesh is unchanged by the move.

    Args:
        verts: ``(N, 3)`` canonical vertices ``X^0`` (object frame).
        weights: ``(N, B)`` skinning weights W.
        centers: ``(B, 3)`` current centres C.

    Returns:
        ``(B, 3)`` float64 new centres.
    """
    X, W, C = _bones_in("shift_bones", verts, weights, centers)
    lab = assign_parts(W)
    B = W.shape[1]
    count = np.bincount(lab, minlength=B).astype(np.float64)
    sums = np.zeros((B, 3))
    np.add.at(sums, lab, X)
    out = C.copy()
    has = count > 0
    out[has] = sums[has] / count[has, None]
    return out


def fit_bones_to_parts(verts, faces, face_parts, centers, precisions, min_faces: int = 4):
    """Each bone onto its labelled part: centre to the part's area centroid, long axis to its principal axis.

    The coarse phase's bones are chords of the 2D skeleton's edges, and its part-silhouette loss moves each
    edge's faces onto that edge's pixels: a curved part (a tail rising from the rump) ends up beside its
    chord, outside the bone's Gaussian, and the body's wider Gaussian takes its vertices. Bone b's part is
    the faces with ``face_parts == b``; a part of fewer than ``min_faces`` faces (or no area) leaves its
    bone as it is. The precision is turned by the smallest rotation that takes its long axis (the
    eigenvector of its smallest eigenvalue) onto the part's principal axis, so the radii are kept.

    Args:
        verts: ``(N, 3)`` canonical vertices.
        faces: ``(F, 3)`` vertex indices.
        face_parts: ``(F,)`` bone index of each face (< 0 or >= B: no bone).
        centers: ``(B, 3)`` bone centres C.
        precisions: ``(B, 3, 3)`` precisions Q.
        min_faces: the fewest faces a part needs to move its bone.

    Returns:
        ``(centers (B, 3), precisions (B, 3, 3), moved (B,) bool)``, float64.
    """
    X = _np(verts)
    Fc = np.asarray(faces, dtype=np.int64)
    fp = np.asarray(face_parts, dtype=np.int64).reshape(-1)
    C, Q = _np(centers).copy(), _np(precisions).copy()
    B = C.shape[0]
    _check("fit_bones_to_parts", "verts", X, (None, 3))
    _check("fit_bones_to_parts", "faces", Fc, (None, 3))
    _check("fit_bones_to_parts", "centers", C, (None, 3))
    _check("fit_bones_to_parts", "precisions", Q, (B, 3, 3))
    if len(fp) != len(Fc):
        raise ValueError(f"fit_bones_to_parts(): face_parts has {len(fp)} entries for {len(Fc)} faces; "
                         "pass one part index per face")
    tri = X[Fc]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    mid = tri.mean(1)
    moved = np.zeros(B, bool)
    for b in range(B):
        sel = fp == b
        w = area[sel]
        if sel.sum() < min_faces or not w.sum() > 0:
            continue
        c = (w[:, None] * mid[sel]).sum(0) / w.sum()
        d = mid[sel] - c
        axis = np.linalg.eigh((w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0) / w.sum())[1][:, -1]
        old = np.linalg.eigh(0.5 * (Q[b] + Q[b].T))[1][:, 0]  # the long axis: the smallest precision
        if axis @ old < 0:
            axis = -axis
        v = np.cross(old, axis)  # the turn old -> axis, about v by its angle (< 90 degrees after the flip)
        R = axis_angle_to_matrix(torch.as_tensor(v / max(np.linalg.norm(v), 1e-300)
                                                 * np.arctan2(np.linalg.norm(v), old @ axis))).numpy()
        C[b], Q[b] = c, R @ Q[b] @ R.T
        moved[b] = True
    return C, 0.5 * (Q + np.transpose(Q, (0, 2, 1))), moved


# ---------------------------------------------------------------------------------------------------
# splitting machinery (growth, upsampling, joint creation)
# ---------------------------------------------------------------------------------------------------


def _sections(t: np.ndarray, k: int, mode: str) -> np.ndarray:
    """Section index (0..k-1) of each projection t: equal vertex counts or equal lengths along t."""
    if mode == "count":
        order = np.argsort(t, kind="stable")
        sec = np.empty(len(t), np.int64)
        sec[order] = (np.arange(len(t)) * k) // max(len(t), 1)
        return sec
    lo, hi = float(t.min()), float(t.max())
    return np.clip(((t - lo) / max(hi - lo, 1e-12) * k).astype(np.int64), 0, k - 1)


def _apply_splits(X, W, C, Q, P, splits: dict, sharpness: float, extents=None) -> SkeletonEdit:
    """Replace each bone b in ``splits`` (b -> per-vertex section labels of its part, 0 nearest the parent)
    by a chain of bones at the section centroids: parent(b) -> s0 -> s1 -> ...; b's children hang from
    the section nearest to them (smallest distance from the child's centre to the section's vertices)."""
    lab = assign_parts(W)
    B = len(C)
    new_of_old: list[list[int]] = []
    centers, precs, sources, kept, ext = [], [], [], [], []
    section_pts: dict[int, list[np.ndarray]] = {}
    for b in range(B):
        if b not in splits:
            new_of_old.append([len(centers)])
            centers.append(C[b])
            precs.append(Q[b])
            sources.append([(b, 1.0)])
            kept.append(True)
            ext.append(np.nan if extents is None else extents[b])
            continue
        pts = X[lab == b]
        sec = splits[b]
        ids = []
        section_pts[b] = []
        for s in range(int(sec.max()) + 1):
            ps = pts[sec == s]
            ids.append(len(centers))
            centers.append(ps.mean(0))
            precs.append(precision_from_points(ps, sharpness, fallback=Q[b]))
            sources.append([(b, 1.0)])
            kept.append(False)
            section_pts[b].append(ps)
            ext.append(_diameter(ps))
        new_of_old.append(ids)
    parents = np.full(len(centers), -1, np.int64)
    for b in range(B):
        ids = new_of_old[b]
        pb = int(P[b])
        parents[ids[0]] = -1 if pb < 0 else new_of_old[pb][-1] if pb in splits else new_of_old[pb][0]
        for a, c in zip(ids[:-1], ids[1:]):
            parents[c] = a
    # children of split bones: attach to the nearest section (others were set above through new_of_old[pb])
    for b in range(B):
        pb = int(P[b])
        if pb >= 0 and pb in splits:
            d = [np.min(np.linalg.norm(ps - C[b], axis=1)) for ps in section_pts[pb]]
            parents[new_of_old[b][0]] = new_of_old[pb][int(np.argmin(d))]
    # new joints between consecutive sections at the midpoint of their centres
    joints = [(a, c) for b in splits for a, c in zip(new_of_old[b][:-1], new_of_old[b][1:])]
    jpos = [0.5 * (centers[a] + centers[c]) for a, c in joints]
    return SkeletonEdit(
        np.asarray(centers, np.float64).reshape(-1, 3), np.asarray(precs, np.float64).reshape(-1, 3, 3), parents,
        sources, np.asarray(kept, bool), None if extents is None else np.asarray(ext, np.float64),
        np.asarray(joints, np.int64).reshape(-1, 2), np.asarray(jpos, np.float64).reshape(-1, 3))


def _principal_axis(p: np.ndarray) -> np.ndarray:
    c = p - p.mean(0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    return vt[0]


# ---------------------------------------------------------------------------------------------------
# skeleton growth
# ---------------------------------------------------------------------------------------------------


def grow_skeleton(
    verts,
    weights,
    centers,
    precisions,
    parents,
    initial_extents,
    growth_factor: float = 2.0,
    sections: int = 2,
    split: Literal["count", "length"] = "count",
    anchors=None,
    sharpness: float = DEFAULT_SHARPNESS,
    min_section_vertices: int = 4,
) -> SkeletonEdit:
    """Skeleton growth (paper 3.4): split stretched end parts into ``sections`` bones along the growth direction.

    An end part is the part ``I_b`` of a leaf bone (no children). It grows when its maximum internal
    distance (:func:`part_extents`) exceeds ``growth_factor`` x its reference value ``initial_extents[b]``
    (a reference of 0, a bone that had no part when measured, never grows).
    The growth direction is the unit vector from the connected point on the skeleton (``anchors[b]``:
    the joint with the parent; default the parent's centre) to the end part's centroid (the paper's
    "endpoint"); a root leaf (one-bone skeleton) uses its part's principal axis. The part's vertices
    are projected on the direction and cut into ``sections`` equal-count (``split="count"``) or
    equal-length (``"length"``) sections; each becomes a bone at the section centroid with the
    section's covariance precision, chained parent -> section 1 (nearest the anchor) -> ... -> section k.
    Both halves of the motion come from the old bone (exact copy, see :func:`s3o_warp.skeleton.remap.remap_bones`).

    Args:
        verts: ``(N, 3)`` canonical vertices. weights: ``(N, B)`` W. centers: ``(B, 3)`` C.
        precisions: ``(B, 3, 3)`` Q. parents: ``(B,)`` int tree (-1 root).
        initial_extents: ``(B,)`` reference extents (object units; :func:`part_extents` at the start of
            phase 2, then the ``extents`` of the previous edit).
        growth_factor: growth threshold on extent / reference extent (paper: 2).
        sections: k, bones an end part is split into (paper: 2).
        split: equal-count or equal-length sections.
        anchors: optional ``(B, 3)`` joint position of each bone with its parent (NaN rows = unknown).
        sharpness: precision scale of the new bones.
        min_section_vertices: a part whose sections would have fewer vertices is left alone.

    Returns:
        A :class:`SkeletonEdit` whose ``extents`` are the references for the next growth test (the
        new sections' own diameters; unchanged bones keep theirs).
    """
    X, W, C, Q, P = _bones_in("grow_skeleton", verts, weights, centers, precisions, parents)
    B = W.shape[1]
    E0 = _np(initial_extents)
    _check("grow_skeleton", "initial_extents", E0, (B,))
    if growth_factor <= 0 or sections < 2:
        raise ValueError(f"grow_skeleton(): need growth_factor > 0 and sections >= 2, got {growth_factor}, {sections}")
    if split not in ("count", "length"):
        raise ValueError(f"grow_skeleton(): split must be 'count' or 'length', got {split!r}")
    A = None if anchors is None else _np(anchors)
    if A is not None:
        _check("grow_skeleton", "anchors", A, (B, 3))
    ext = part_extents(X, W)
    lab = assign_parts(W)
    kids = children_of(P)
    splits = {}
    for b in range(B):
        if kids[b] or not E0[b] > 0 or not ext[b] > growth_factor * E0[b]:
            continue
        pts = X[lab == b]
        if len(pts) < sections * min_section_vertices:
            continue
        cen = pts.mean(0)
        anchor = None
        if A is not None and np.isfinite(A[b]).all():
            anchor = A[b]
        elif P[b] >= 0:
            anchor = C[P[b]]
        d = None if anchor is None else cen - anchor
        if d is None or np.linalg.norm(d) < 1e-9:
            d = _principal_axis(pts)
            anchor = cen - d
        d = d / np.linalg.norm(d)
        sec = _sections((pts - anchor) @ d, sections, split)
        if np.bincount(sec, minlength=sections).min() < min_section_vertices:
            continue
        splits[b] = sec
        log.info("grow_skeleton: end bone %d stretched %.2fx its reference; split into %d",
                 b, ext[b] / max(E0[b], 1e-12), sections)
    if not splits:
        return _identity_edit(C, Q, P, E0)
    edit = _apply_splits(X, W, C, Q, P, splits, sharpness, extents=E0)
    return edit


# ---------------------------------------------------------------------------------------------------
# skeleton upsampling (Alg. 1, epoch e1)
# ---------------------------------------------------------------------------------------------------


def upsample_skeleton(
    verts,
    weights,
    centers,
    precisions,
    parents,
    sharpness: float = DEFAULT_SHARPNESS,
    min_section_vertices: int = 4,
    extents=None,
) -> SkeletonEdit:
    """One skeleton upsampling (Alg. 1 at epoch e1): split bones in two along their part's principal axis.

    Every bone is split at the median projection on the principal axis of ``I_b`` (equal vertex
    counts). The half nearer to the parent's centre keeps the parent (for a root: the half lower in
    the axis' dominant coordinate stays the root); the other half is its child; children of the old
    bone hang from the half nearer to them.

    Args:
        verts, weights, centers, precisions, parents: as in :func:`grow_skeleton`.
        sharpness: precision scale of the new bones.
        min_section_vertices: bones with fewer than twice this many part vertices are not split.
        extents: optional ``(B,)`` growth references to carry through the edit.

    Returns:
        A :class:`SkeletonEdit`.
    """
    X, W, C, Q, P = _bones_in("upsample_skeleton", verts, weights, centers, precisions, parents)
    ext = part_extents(X, W)
    lab = assign_parts(W)
    splits = {}
    for b in range(W.shape[1]):
        pts = X[lab == b]
        if len(pts) < 2 * min_section_vertices or ext[b] <= 0:
            continue
        d = _principal_axis(pts)
        if P[b] >= 0:
            if (C[P[b]] - pts.mean(0)) @ d > 0:
                d = -d  # section 0 = the half nearer the parent
        elif d[np.argmax(np.abs(d))] < 0:
            d = -d  # a root: section 0 = the lower half along the axis' dominant coordinate
        splits[b] = _sections((pts - pts.mean(0)) @ d, 2, "count")
    if not splits:
        return _identity_edit(C, Q, P, extents)
    return _apply_splits(X, W, C, Q, P, splits, sharpness, extents=None if extents is None else _np(extents))


# ---------------------------------------------------------------------------------------------------
# bone merging (eqs. 8-9, log-space weights) and pruning
# ---------------------------------------------------------------------------------------------------


def merge_bones(
    similarity,
    weights,
    centers,
    precisions,
    parents,
    t_o: float = 0.95,
    temperature: float = 1.0,
    extents=None,
) -> SkeletonEdit:
    """Merge bones that move together (eqs. 8-9): ``min_f S(F_b', F_b'') > t_o`` for tree neighbours.

    Only bones adjacent in the kinematic tree (parent and child) are candidates, so a merge keeps a
    tree. Candidate pairs are taken in decreasing similarity, each bone merged at most once per call (the
    paper's pairwise rule; repeated M-steps merge longer chains).

    The merged bone is ``B~ = sum_i w_i B_i`` for the centres C and precisions Q, with
    ``w = softmax(S / temperature)`` over the members' weight masses ``S_i = sum_n W[n, i]``. The paper
    writes ``w' = exp(S') / (exp(S') + exp(S''))``, which overflows for thousands of vertices; the
    softmax in log space is the same number without overflow. ``temperature = 1``
    is the paper's formula (then the larger part nearly always wins outright); larger values blend.
    The merged bone's motion is the same blend of its members' motions; its length comes from its
    joints afterwards (:func:`s3o_warp.skeleton.measures.bone_lengths`).

    Args:
        similarity: ``(B, B)`` motion similarity (:func:`s3o_warp.skeleton.measures.motion_similarity`).
        weights: ``(N, B)`` W. centers: ``(B, 3)``. precisions: ``(B, 3, 3)``. parents: ``(B,)``.
        t_o: merge threshold (paper: 0.95; 0.99 finer, 0.90 coarser skeletons).
        temperature: softmax temperature of the merge weights (1 = paper).
        extents: optional ``(B,)`` growth references; a merged bone gets the blend of its members'.

    Returns:
        A :class:`SkeletonEdit` (merged bones take the index of their lowest member, others keep order).
    """
    B = _np(weights).shape[1]
    Sim = _np(similarity)
    _check("merge_bones", "similarity", Sim, (B, B))
    P = _np(parents, np.int64)
    _check("merge_bones", "parents", P, (B,))
    cand = [(float(min(Sim[b, p], Sim[p, b])), int(p), b) for b, p in enumerate(P) if p >= 0]
    cand = [c for c in cand if c[0] > t_o]
    cand.sort(key=lambda c: -c[0])
    used = np.zeros(B, bool)
    pairs = []
    for _s, a, b in cand:
        if not (used[a] or used[b]):
            used[a] = used[b] = True
            pairs.append((a, b))
    return _merge_pairs("merge_bones", pairs, weights, centers, precisions, P, temperature, extents)


def _merge_pairs(name: str, pairs, weights, centers, precisions, parents, temperature: float, extents) -> SkeletonEdit:
    """The edit of :func:`merge_bones` and :func:`prune_short_bones`: each connected component of the tree
    edges ``pairs`` becomes one bone, blended with ``softmax(S / temperature)`` of its members' weight masses."""
    Wn = _np(weights)
    B = Wn.shape[1]
    C = _np(centers)
    _check(name, "centers", C, (B, 3))
    Q = _np(precisions)
    _check(name, "precisions", Q, (B, 3, 3))
    P = _np(parents, np.int64)
    _check(name, "parents", P, (B,))
    if temperature <= 0:
        raise ValueError(f"{name}(): temperature must be > 0, got {temperature}")
    root = list(range(B))

    def find(a: int) -> int:
        while root[a] != a:
            root[a] = root[root[a]]
            a = root[a]
        return a

    for a, b in pairs:
        ra, rb = find(a), find(b)
        if ra != rb:
            root[max(ra, rb)] = min(ra, rb)
    groups: dict[int, list[int]] = {}
    for b in range(B):
        groups.setdefault(find(b), []).append(b)
    if all(len(g) == 1 for g in groups.values()):
        return _identity_edit(C, Q, P, extents)
    S = Wn.sum(0)
    order = sorted(groups)  # new bone j = group with the j-th smallest lowest member
    new_of_old = np.empty(B, np.int64)
    centers, precs, sources, kept, ext = [], [], [], [], []
    E0 = None if extents is None else _np(extents)
    for j, g0 in enumerate(order):
        g = groups[g0]
        new_of_old[g] = j
        logits = S[g] / temperature
        w = np.exp(logits - logits.max())
        w /= w.sum()
        centers.append(np.einsum("i,ic->c", w, C[g]))
        precs.append(np.einsum("i,ijk->jk", w, Q[g]))
        sources.append([(int(i), float(wi)) for i, wi in zip(g, w)])
        kept.append(len(g) == 1)
        ext.append(np.nan if E0 is None else float(w @ E0[g]))
        if len(g) > 1:
            log.info("merge_bones: merged bones %s (weights %s)", g, np.round(w, 3).tolist())
    parents = np.full(len(order), -1, np.int64)
    for j, g0 in enumerate(order):
        outside = [int(P[i]) for i in groups[g0] if P[i] >= 0 and find(int(P[i])) != g0]
        parents[j] = new_of_old[outside[0]] if outside else -1
    return SkeletonEdit(np.asarray(centers), np.asarray(precs), parents, sources, np.asarray(kept, bool),
                        None if E0 is None else np.asarray(ext))


def prune_short_bones(lengths, min_length: float, weights, centers, precisions, parents, extents=None) -> SkeletonEdit:
    """Merge every inner bone shorter than ``min_length``, and every bone that owns no vertex, into its
    parent (a root: into its longest child).

    Not in the paper. Joint creation (eq. 6) compares a bone's length range with its own median, so a
    short bone at a strongly bending joint (a hip, a shoulder) keeps qualifying and is split again and
    again into a knot of ever shorter bones; an upsampled or split bone can also end up owning no vertex
    at all, whatever its length (an inner one's two joints then fall back to its neighbours' borders, which
    can lie far apart: a leg's top joint at the tail's base). Such bones carry no motion of their own that
    their neighbours do not, and they clutter the exported rig. A short end bone (no children) that owns vertices is kept: it is a tail tip, an
    ear or a hoof. The pairs (short bone, neighbour) are merged as by :func:`merge_bones` with the paper's
    weights (temperature 1), but all at once: each connected group of pairs becomes one bone, so a chain of
    short bones collapses into the long bone it hangs from, whose centre, precision and motion win by their
    weight mass.

    Args:
        lengths: ``(B,)`` canonical bone lengths (:func:`s3o_warp.skeleton.measures.bone_lengths`).
        min_length: bones with ``lengths < min_length`` are merged (same units as ``lengths``); 0 = only the
            empty ones.
        weights, centers, precisions, parents, extents: as in :func:`merge_bones`.

    Returns:
        A :class:`SkeletonEdit` (the identity when no bone is short or empty, or the only bone is).
    """
    L = _np(lengths)
    P = _np(parents, np.int64)
    B = len(P)
    _check("prune_short_bones", "lengths", L, (B,))
    if min_length < 0:
        raise ValueError(f"prune_short_bones(): min_length must be >= 0, got {min_length}")
    kids = children_of(P)
    owned = np.bincount(assign_parts(_np(weights)), minlength=B)[:B]
    kids = [[c for c in k if owned[c] > 0] for k in kids]  # empty children go anyway: they do not make an inner bone
    short, pairs = [], []
    for b in np.flatnonzero((L < min_length) | (owned == 0)):  # an empty bone's joints can lie far apart
        b = int(b)
        if not (kids[b] or owned[b] == 0):
            continue  # a short end bone with vertices: kept
        if P[b] < 0 and not kids[b]:
            continue  # a lone root: nothing to merge with
        pairs.append((b, int(P[b]) if P[b] >= 0 else max(kids[b], key=lambda c: L[c])))
        short.append(b)
    if not short:
        return _identity_edit(_np(centers), _np(precisions), P, extents)
    log.info("prune_short_bones: bones %s shorter than %.4g or empty", short, min_length)
    return _merge_pairs("prune_short_bones", pairs, weights, centers, precisions, P, 1.0, extents)


__all__ = [
    "DEFAULT_SHARPNESS",
    "SkeletonEdit",
    "fit_bones_to_parts",
    "grow_skeleton",
    "merge_bones",
    "precision_from_points",
    "precision_to_quat_scales",
    "prune_short_bones",
    "shift_bones",
    "upsample_skeleton",
]
