"""Skeleton edits of the M-step (paper 3.4): bone shifting, growth, upsampling, joint creation, merging.

Every edit is a pure function of the canonical vertices ``X^0 = M_c`` ``(N, 3)``, the skinning
weights ``W`` ``(N, B)`` and the current bones (centres ``C`` ``(B, 3)``, precisions ``Q`` ``(B, 3, 3)``,
kinematic tree ``parents`` ``(B,)`` with -1 for a root), all in the canonical object frame. An edit
returns a :class:`SkeletonEdit`: the new bone list plus, for each new bone, the old bones (with
weights) whose motion it inherits. :func:`remap_bones` then applies that to an ``S3OModel`` and its
Adam optimiser in place, so the posed mesh does not jump.

Notation: ``I_b`` the vertices whose argmax weight is bone b (the "semi-rigid part" of b, eq. 5);
``S_b = sum_n W[n, b]`` a bone's weight mass. A section's precision comes from its vertices'
covariance: ``Q = sharpness * (Sigma + eps tr(Sigma)/3 I)^-1``. With the default sharpness 2/3, points
on the surface of an ellipsoid with radii r (surface variance r^2/3 per axis) get ``Q = 2 / r^2``: the
precision the coarse initialisation gives the same ellipsoid with ``precision_sharpness = 2``.

Inputs may be numpy arrays or torch tensors; outputs are float64/int64 numpy arrays.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal, Sequence

import numpy as np
import torch

from s3o_warp.geometry import to_numpy as _np

log = logging.getLogger(__name__)

DEFAULT_SHARPNESS = 2.0 / 3.0
"""Precision of a new bone = sharpness x inverse covariance of its vertices (see module docstring)."""


# ---------------------------------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------------------------------


def _check(name: str, arg: str, a: np.ndarray, shape: tuple) -> None:
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        want = "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name}(): {arg} must have shape {want}, got {tuple(a.shape)}")


def _bones_in(name: str, verts, weights, centers=None, precisions=None, parents=None):
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


def assign_parts(weights) -> np.ndarray:
    """``(N,)`` int64 argmax bone of each vertex: vertex n belongs to the part ``I_b`` of ``b = argmax_b W[n, b]``."""
    return np.argmax(_np(weights), axis=1).astype(np.int64)


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
    from s3o_warp.geometry import matrix_to_quat

    Q = _np(precisions).reshape(-1, 3, 3)
    lam, U = np.linalg.eigh(0.5 * (Q + np.transpose(Q, (0, 2, 1))))
    V = np.transpose(U, (0, 2, 1)).copy()
    V[np.linalg.det(V) < 0, 2] *= -1  # proper rotations (flipping an axis leaves Q unchanged)
    quats = matrix_to_quat(torch.as_tensor(V)).numpy()
    return quats, np.log(np.maximum(lam, 1e-12))


def part_extents(verts, weights) -> np.ndarray:
    """``(B,)`` maximum internal distance of each part ``I_b`` (diameter of its argmax vertices; 0 if < 2).

    The diameter is exact: the farthest pair of a point set lies on its convex hull (scipy's Qhull,
    joggled for flat sets), so only hull vertices are compared.
    """
    X, W = _bones_in("part_extents", verts, weights)
    lab = assign_parts(W)
    return np.array([_diameter(X[lab == b]) for b in range(W.shape[1])], np.float64)


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
    :func:`remap_bones` (identity ``sources``), which re-pivots each bone's per-frame translation so the
    posed mesh is unchanged by the move.

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
    from s3o_warp.geometry import axis_angle_to_matrix

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


def _diameter(p: np.ndarray) -> float:
    """Largest pairwise distance of a point set (0 for fewer than 2 points)."""
    from scipy.spatial import ConvexHull
    from scipy.spatial.distance import pdist

    if len(p) < 2:
        return 0.0
    if len(p) > 64:
        try:
            p = p[ConvexHull(p, qhull_options="QJ").vertices]
        except Exception:  # noqa: BLE001 - Qhull fails on degenerate sets; the pairwise check is exact anyway
            pass
    return float(pdist(p).max())


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
    Both halves of the motion come from the old bone (exact copy, see :func:`remap_bones`).

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
# joint creation (eqs. 6-7, corrected)
# ---------------------------------------------------------------------------------------------------


def _cut_inputs(name: str, X: np.ndarray, W: np.ndarray, endpoints, bones):
    """The checked ``(B,)`` selection, the canonical endpoints ``(B, 2, 3)`` and the parts, for a midpoint cut."""
    B = W.shape[1]
    E = _np(endpoints)
    _check(name, "endpoints", E, (B, 2, X.shape[0]))
    sel = _np(bones, bool)
    _check(name, "bones", sel, (B,))
    return sel, np.einsum("bkn,nc->bkc", E, X), assign_parts(W)


def _midpoint_cut(X, lab, ends, C, P, b: int, min_section_vertices: int):
    """Bone b's part cut by the plane through its endpoints' midpoint m, perpendicular to them: ``(sec, m)``
    with ``sec`` 0 on the parent's side and 1 beyond (over the part's vertices, in order), or None when a side
    would own fewer than ``min_section_vertices``."""
    pts = X[lab == b]
    d = ends[b, 1] - ends[b, 0]
    if np.linalg.norm(d) < 1e-12 or len(pts) < 2 * min_section_vertices:
        return None
    m = ends[b].mean(0)
    if P[b] >= 0 and (C[P[b]] - m) @ d > 0:
        d = -d
    sec = ((pts - m) @ d > 0).astype(np.int64)
    if np.bincount(sec, minlength=2).min() < min_section_vertices:
        return None
    return sec, m


def bone_halves(verts, weights, centers, parents, endpoints, bones, min_section_vertices: int = 4):
    """The two halves :func:`split_at_joints` would cut the selected bones' parts into, as blend weights.

    Returns ``(halves, W2)``: the bones that can be cut ``(K,)`` and ``(N, 2K)`` weights, columns ``2k`` (the
    parent's side) and ``2k + 1`` (beyond) holding bone ``halves[k]``'s weights on its part's vertices of that
    half, 0 elsewhere (for :func:`s3o_warp.skeleton.measures.bone_flow` and :func:`s3o_warp.skeleton.measures.unexplained_motion`).
    """
    X, W, C, P = _bones_in("bone_halves", verts, weights, centers, parents=parents)
    sel, ends, lab = _cut_inputs("bone_halves", X, W, endpoints, bones)
    halves, cols = [], []
    for b in np.flatnonzero(sel):
        cut = _midpoint_cut(X, lab, ends, C, P, int(b), min_section_vertices)
        if cut is None:
            continue
        idx = np.flatnonzero(lab == b)
        for side in (0, 1):
            w = np.zeros(X.shape[0])
            w[idx[cut[0] == side]] = W[idx[cut[0] == side], b]
            cols.append(w)
        halves.append(int(b))
    W2 = np.stack(cols, 1) if cols else np.zeros((X.shape[0], 0))
    return np.asarray(halves, np.int64), W2


def split_at_joints(
    verts,
    weights,
    centers,
    precisions,
    parents,
    endpoints,
    bones,
    sharpness: float = DEFAULT_SHARPNESS,
    min_section_vertices: int = 4,
    extents=None,
) -> SkeletonEdit:
    """Create a joint (eq. 7): split each selected bone in two at the midpoint of its two endpoints.

    The paper places the new joint ``J~`` at the average of the bone's two joints ``J_j``, ``J_j'`` and
    redirects their connection through it. Here: the part ``I_b`` is cut by the plane through the
    midpoint ``m = (e_0 + e_1)/2`` of the bone's canonical endpoints (``endpoints @ verts``, see
    :func:`s3o_warp.skeleton.measures.bone_endpoints`) perpendicular to ``e_1 - e_0``; each side becomes a bone
    (centroid, covariance precision), chained on the parent's side first, with a new joint at m.

    Args:
        verts, weights, centers, precisions, parents: as in :func:`grow_skeleton`.
        endpoints: ``(B, 2, N)`` row-normalised endpoint selection matrix.
        bones: ``(B,)`` bool, which bones get a joint (:func:`s3o_warp.skeleton.measures.create_joints`).
        sharpness, min_section_vertices, extents: as in :func:`upsample_skeleton`.

    Returns:
        A :class:`SkeletonEdit`; ``joint_positions`` holds the midpoints m.
    """
    X, W, C, Q, P = _bones_in("split_at_joints", verts, weights, centers, precisions, parents)
    sel, ends, lab = _cut_inputs("split_at_joints", X, W, endpoints, bones)
    splits, mids = {}, {}
    for b in np.flatnonzero(sel):
        cut = _midpoint_cut(X, lab, ends, C, P, int(b), min_section_vertices)
        if cut is not None:
            splits[int(b)], mids[int(b)] = cut
    if not splits:
        return _identity_edit(C, Q, P, extents)
    edit = _apply_splits(X, W, C, Q, P, splits, sharpness, extents=None if extents is None else _np(extents))
    # the joint of a split bone sits at the endpoints' midpoint (same order as edit.joints: by bone)
    edit.joint_positions = np.asarray([mids[b] for b in splits]).reshape(-1, 3)
    return edit


# ---------------------------------------------------------------------------------------------------
# bone merging (eqs. 8-9, log-space weights)
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


# ---------------------------------------------------------------------------------------------------
# model surgery
# ---------------------------------------------------------------------------------------------------


def _mix(old: torch.Tensor, dim: int, sources: Sequence) -> torch.Tensor:
    """new[..., j, ...] = sum_i w_ji old[..., i, ...] along ``dim``; single weight-1 sources are copied exactly."""
    cols = []
    for src in sources:
        if len(src) == 1 and src[0][1] == 1.0:
            cols.append(old.select(dim, src[0][0]))
        else:
            acc = sum(float(w) * old.select(dim, i) for i, w in src)
            cols.append(acc)
    return torch.stack(cols, dim)


def remap_bones(model, optimizer, sources, centers, quats, log_scales) -> None:
    """Replace the bone set of an ``S3OModel`` in place, carrying motion and Adam state over.

    New ``nn.Parameter`` objects replace ``bone_centers`` ``(B', 3)``, ``bone_quat`` ``(B', 4)`` (w, x, y,
    z), ``bone_log_scales`` ``(B', 3)``, ``bone_aa`` ``(T, B', 3)`` and ``bone_t`` ``(T, B', 3)``.

    Motion: new bone j with sources ``[(i, w_i)]`` gets ``aa_j = sum_i w_i aa_i`` and the translation
    that reproduces the blend of its sources' affine maps about the NEW centre. The model poses bone b
    as ``A_b = [R_b | c_b + t_b - R_b c_b]`` (rotation about its own centre), so with ``R_j = R(aa_j)``::

        t_j = sum_i w_i t_i + sum_i w_i (I - R_i)(c_i - c_j) + (sum_i w_i R_i - R_j) c_j

    For a single source (a split, a shifted or an unchanged bone) ``R_j = R_i`` and ``A_j = A_i``
    exactly: the posed mesh changes only through the skinning weights of the new Gaussians.

    Optimiser: every state tensor of the old parameters that has the parameter's shape (Adam's
    ``exp_avg``, ``exp_avg_sq``, ...) is mapped with the same weights along the bone axis (copied bit
    for bit for single weight-1 sources); other entries (``step``) are copied. The optimiser's
    param_groups then point at the new parameters. Parameters the optimiser does not hold are just
    replaced. ``optimizer`` may be None.

    Args:
        model: the ``S3OModel``.
        optimizer: a ``torch.optim`` optimiser over (some of) the model's parameters, or None.
        sources: one list of ``(old bone, weight)`` per new bone (weights summing to 1).
        centers: ``(B', 3)`` new Gaussian centres. quats: ``(B', 4)`` (w, x, y, z). log_scales: ``(B', 3)``.

    Raises:
        ValueError: mismatched lengths, an out-of-range source index or weights not summing to 1.
    """
    from s3o_warp.geometry import axis_angle_to_matrix

    name = "remap_bones"
    B_old = model.num_bones
    Bn = len(sources)
    ref = model.bone_centers
    dt = dict(dtype=ref.dtype, device=ref.device)

    def as_t(x) -> torch.Tensor:
        return x.detach().to(**dt) if isinstance(x, torch.Tensor) else torch.as_tensor(_np(x), **dt)

    cn, qn, sn = as_t(centers), as_t(quats), as_t(log_scales)
    for arg, t, k in (("centers", cn, 3), ("quats", qn, 4), ("log_scales", sn, 3)):
        if tuple(t.shape) != (Bn, k):
            raise ValueError(f"{name}(): {arg} must have shape ({Bn}, {k}) for {Bn} sources, got {tuple(t.shape)}")
    if Bn == 0:
        raise ValueError(f"{name}(): need at least one new bone")
    for j, src in enumerate(sources):
        if not src or any(not 0 <= int(i) < B_old for i, _ in src):
            raise ValueError(f"{name}(): sources[{j}] must list old bones in [0, {B_old}), got {src}")
        if abs(sum(float(w) for _, w in src) - 1.0) > 1e-6:
            raise ValueError(f"{name}(): sources[{j}] weights must sum to 1, got {src}")
    sources = [[(int(i), float(w)) for i, w in src] for src in sources]
    with torch.no_grad():
        c_old = model.bone_centers.detach()
        aa_old, t_old = model.bone_aa.detach(), model.bone_t.detach()
        aa_new = _mix(aa_old, 1, sources)
        R_old = axis_angle_to_matrix(aa_old)  # (T, B, 3, 3)
        R_new = axis_angle_to_matrix(aa_new)
        t_cols = []
        for j, src in enumerate(sources):
            if len(src) == 1 and src[0][1] == 1.0:
                i = src[0][0]
                dc = c_old[i] - cn[j]
                t_cols.append(t_old[:, i] + dc - (R_old[:, i] @ dc[:, None])[..., 0] if bool((dc != 0).any())
                              else t_old[:, i].clone())
                continue
            acc = torch.zeros_like(t_old[:, 0])
            Rmix = torch.zeros_like(R_old[:, 0])
            for i, w in src:
                dc = c_old[i] - cn[j]
                acc = acc + w * (t_old[:, i] + dc - (R_old[:, i] @ dc[:, None])[..., 0])
                Rmix = Rmix + w * R_old[:, i]
            acc = acc + ((Rmix - R_new[:, j]) @ cn[j][:, None])[..., 0]
            t_cols.append(acc)
        t_new = torch.stack(t_cols, 1)
    new_vals = {
        "bone_centers": (cn.clone(), 0),
        "bone_quat": (qn.clone(), 0),
        "bone_log_scales": (sn.clone(), 0),
        "bone_aa": (aa_new, 1),
        "bone_t": (t_new, 1),
    }
    for attr, (val, dim) in new_vals.items():
        old = getattr(model, attr)
        new = torch.nn.Parameter(val.contiguous().clone(), requires_grad=old.requires_grad)
        if optimizer is not None:
            _move_state(optimizer, old, new, dim, sources, B_old)
        setattr(model, attr, new)
    log.info("remap_bones: %d -> %d bones", B_old, Bn)


def _move_state(optimizer, old: torch.nn.Parameter, new: torch.nn.Parameter, dim: int, sources, B_old: int) -> None:
    held = False
    for g in optimizer.param_groups:
        for k, p in enumerate(g["params"]):
            if p is old:
                g["params"][k] = new
                held = True
    if not held:
        return
    st = optimizer.state.pop(old, None)
    if not st:
        return
    out = {}
    for key, v in st.items():
        if isinstance(v, torch.Tensor) and v.shape == old.shape and v.dim() > dim and v.shape[dim] == B_old:
            out[key] = _mix(v, dim, sources).contiguous().clone()
        else:
            out[key] = v.clone() if isinstance(v, torch.Tensor) else v
    optimizer.state[new] = out


def apply_edit(model, optimizer, edit: SkeletonEdit) -> None:
    """:func:`remap_bones` with an edit's bones; kept bones reuse their exact old quaternion and log-scales."""
    dt = dict(dtype=model.bone_centers.dtype, device=model.bone_centers.device)
    q, s = precision_to_quat_scales(edit.precisions)
    centers = torch.as_tensor(edit.centers, **dt)
    quats, scales = torch.as_tensor(q, **dt), torch.as_tensor(s, **dt)
    for j, src in enumerate(edit.sources):
        if edit.kept[j]:  # bit-exact copies, so an unchanged bone's skinning and optimiser step are unchanged
            i = src[0][0]
            centers[j] = model.bone_centers.detach()[i]
            quats[j] = model.bone_quat.detach()[i]
            scales[j] = model.bone_log_scales.detach()[i]
    remap_bones(model, optimizer, edit.sources, centers, quats, scales)


__all__ = [
    "DEFAULT_SHARPNESS",
    "SkeletonEdit",
    "apply_edit",
    "assign_parts",
    "children_of",
    "grow_skeleton",
    "merge_bones",
    "part_extents",
    "precision_from_points",
    "precision_to_quat_scales",
    "prune_short_bones",
    "remap_bones",
    "shift_bones",
    "split_at_joints",
    "tree_joints",
    "upsample_skeleton",
]
