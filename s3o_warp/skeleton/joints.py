"""Joints (paper 3.4, "Joint Positions and Bone Lengths Calculation", and joint creation, eq. 7): a joint
``J_ij`` of bones i and j sits at the mean of the vertices both weigh at least t_r (here over points spread over
the surface, and then moved into the body: neither in the paper); each bone's two ends, whose distance is its
length in eq. 6, are chosen once on the canonical mesh from its joints and then follow the vertices; and a bone
whose length varies over the frames (eq. 6, :func:`s3o_warp.skeleton.measures.create_joints`) is split in two at
the midpoint of its ends, with the new joint there (eq. 7), as a :class:`s3o_warp.skeleton.edit.SkeletonEdit`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from s3o_warp.ops import closest_point, ray_hit
from s3o_warp.skeleton.edit import (
    DEFAULT_SHARPNESS,
    SkeletonEdit,
    _apply_splits,
    _identity_edit,
)
from s3o_warp.skeleton.measures import _bones_in, _check, _np, assign_parts, size_of

# ---------------------------------------------------------------------------------------------------
# joint positions (paper 3.4, t_r)
# ---------------------------------------------------------------------------------------------------


class SurfaceSamples(NamedTuple):
    """Points spread over a mesh's surface, each a barycentric mix of one face's three vertices.

    ``index`` ``(S, 3)`` vertex indices, ``bary`` ``(S, 3)`` weights (rows sum to 1; the point is
    ``bary @ X[index]``), ``weights`` ``(S, B)`` the Gaussian bones' skinning weights at the points.
    """

    index: np.ndarray
    bary: np.ndarray
    weights: np.ndarray


def gaussian_weights(points, centers, precisions) -> np.ndarray:
    """``(S, B)`` ``softmax_b(-1/2 (x - C_b)^T Q_b (x - C_b))`` at ``(S, 3)`` points: the skinning weights of
    the Gaussian bones anywhere (float64 twin of :func:`s3o_warp.kernels.skinning.skinning_weights`)."""
    X, C, Q = _np(points).reshape(-1, 3), _np(centers).reshape(-1, 3), _np(precisions).reshape(-1, 3, 3)
    d = X[:, None, :] - C[None]
    logits = -0.5 * np.einsum("sbi,bik,sbk->sb", d, Q, d)
    w = np.exp(logits - logits.max(1, keepdims=True))
    return w / w.sum(1, keepdims=True)


def surface_samples(verts, faces, centers, precisions, level: int) -> SurfaceSamples | None:
    """Each face's barycentric grid of step ``1 / level``: the vertices once, ``level - 1`` points inside each
    edge once and the grid's inner points once per face (``level**2`` small triangles per face, evenly covered),
    with the Gaussian bones' weights there. ``level`` <= 1: None (the vertices alone)."""
    if level <= 1:
        return None
    X, F = _np(verts), _np(faces, np.int64)
    if F.ndim != 2 or F.shape[1] != 3:
        raise ValueError(f"surface_samples(): faces must have shape (F, 3), got {F.shape}")
    L = int(level)
    N = len(X)
    idx = [np.stack([np.arange(N)] * 3, 1)]
    bary = [np.tile([1.0, 0.0, 0.0], (N, 1))]
    e = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), 1), axis=0)
    for m in range(1, L):
        t = m / L
        idx.append(np.stack([e[:, 0], e[:, 1], e[:, 1]], 1))
        bary.append(np.tile([1.0 - t, t, 0.0], (len(e), 1)))
    inner = [(i, j, L - i - j) for i in range(1, L) for j in range(1, L) if L - i - j >= 1]
    for i, j, k in inner:
        idx.append(F)
        bary.append(np.tile([i / L, j / L, k / L], (len(F), 1)))
    index, b = np.concatenate(idx), np.concatenate(bary)
    points = np.einsum("sk,skc->sc", b, X[index])
    return SurfaceSamples(index, b, gaussian_weights(points, centers, precisions))


def joint_selection(weights, pairs, t_r: float = 0.4, fallback_count: int = 4,
                    samples: SurfaceSamples | None = None) -> np.ndarray:
    """``(J, N)`` row-normalised selection: joint positions are ``selection @ X``.

    Row j is uniform over ``V_ij = {n : W[n,i] >= t_r and W[n,j] >= t_r}`` (paper 3.4, "Joint
    Positions"). When ``V_ij`` is empty (the bones barely overlap), the row is uniform over the
    ``fallback_count`` vertices with the largest ``min(W[n,i], W[n,j])``: the points most shared
    by both bones, which lie on their boundary.

    With ``samples`` (:func:`surface_samples`; not in the paper) the same is done over those points, with
    their own weights, instead of the vertices: on a coarse mesh the band where two bones' weights both
    reach t_r often falls between the vertices of a thin leg, and the joint, taken from the few vertices
    nearest to it, sits off the boundary. Each chosen point spreads its share over its face's vertices
    (its barycentric weights), so the row still selects vertices and follows the posed mesh.
    """
    W = _np(weights)
    P = _np(pairs, np.int64).reshape(-1, 2)
    if W.ndim != 2:
        raise ValueError(f"joint_selection(): weights must have shape (N, B), got {W.shape}")
    if ((P < 0) | (P >= W.shape[1])).any():
        raise ValueError(f"joint_selection(): pairs must index bones in [0, {W.shape[1]})")
    if samples is not None and samples.weights.shape[1] != W.shape[1]:
        raise ValueError(f"joint_selection(): samples have weights of {samples.weights.shape[1]} bones, "
                         f"weights {W.shape[1]}")
    Ws = W if samples is None else _np(samples.weights)
    out = np.zeros((len(P), W.shape[0]))
    for j, (a, b) in enumerate(P):
        m = np.minimum(Ws[:, a], Ws[:, b])
        sel = m >= t_r
        if not sel.any():
            sel = np.zeros(len(m), bool)
            sel[np.argsort(-m, kind="stable")[: max(1, fallback_count)]] = True
        if samples is None:
            out[j, sel] = 1.0 / sel.sum()
        else:
            np.add.at(out[j], samples.index[sel].ravel(), samples.bary[sel].ravel() / sel.sum())
    return out


def joint_positions(verts, weights, pairs, t_r: float = 0.4, fallback_count: int = 4,
                    samples: SurfaceSamples | None = None) -> np.ndarray:
    """Joint positions ``J_ij = mean of X_n over V_ij`` (see :func:`joint_selection` for the empty case).

    Args:
        verts: ``(N, 3)`` canonical or ``(T, N, 3)`` posed vertices (any frame; the result is in it).
        weights: ``(N, B)`` W. pairs: ``(J, 2)`` bone pairs (i, j).
        t_r: weight threshold (paper: 0.4).
        fallback_count: vertices averaged when ``V_ij`` is empty.
        samples: points over the surface to take ``V_ij`` from instead of the vertices (:func:`joint_selection`).

    Returns:
        ``(J, 3)`` or ``(T, J, 3)`` float64 positions.
    """
    X = _np(verts)
    if X.shape[-1] != 3 or X.ndim not in (2, 3):
        raise ValueError(f"joint_positions(): verts must have shape (N, 3) or (T, N, 3), got {X.shape}")
    Ssel = joint_selection(weights, pairs, t_r, fallback_count, samples)
    if Ssel.shape[1] != X.shape[-2]:
        raise ValueError(f"joint_positions(): weights have {Ssel.shape[1]} vertices, verts {X.shape[-2]}")
    return np.einsum("jn,...nc->...jc", Ssel, X)


def centre_in_body(points, verts, faces, iterations: int = 2, max_depth: float = 0.03, inset: float = 1e-3
                   ) -> np.ndarray:
    """Move points (joints) into the body: onto a thin limb's axis, a little way into a thick part.

    The mean of the vertices two bones share lies on the surface wherever those vertices are on one
    side of a limb. Each iteration takes the point's nearest surface point c (distance a, direction u
    from the point to c) and casts one ray from the point away from c to the opposite wall: the chord
    through the body there has length a + b. The wanted depth below c is h = min(chord / 2,
    ``max_depth`` x the bounding-box diagonal); a point shallower than h moves to ``c - h u``, a deeper
    one stays. So a point in a thin limb goes to the middle of its cross-section (for a tube, on the
    axis), and a hip joint at the side of the torso goes just inside it instead of onto the midline.
    A point outside, or within ``inset`` of the surface, starts ``inset`` inside c along the surface
    normal there (the face's; on an edge or a vertex, the area-weighted vertex normals interpolated
    over the face). A point still outside
    after that (a spike tip or a fold, where no normal points inwards) goes to the nearest of the chord
    middles cast inward from every vertex.

    Args:
        points: ``(J, 3)`` positions in the mesh's frame.
        verts: ``(N, 3)``; faces: ``(F, 3)`` a closed, consistently wound mesh.
        iterations: passes.
        max_depth: deepest a point is moved below the surface, as a fraction of the bounding-box diagonal.
        inset: how far inside the surface a point on it starts, as a fraction of that diagonal.

    Returns:
        ``(J, 3)`` float64 positions.
    """
    P = _np(points).reshape(-1, 3).copy()
    if len(P) == 0:
        return P
    X = _np(verts)
    Fi = _np(faces, np.int64)
    V = torch.as_tensor(X)
    F = torch.as_tensor(Fi)
    tri = X[Fi]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # area-weighted face normals
    vn = np.zeros_like(X)
    for k in range(3):
        np.add.at(vn, Fi[:, k], fn)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-30)
    diag = size_of(X)
    eps, cap = inset * diag, max_depth * diag
    for _ in range(max(0, iterations)):
        d, f, b = closest_point(V, F, torch.as_tensor(P))
        d, f, b = d.double().numpy(), f.numpy(), b.double().numpy()
        c = np.einsum("jk,jkc->jc", b, tri[f])
        # the face's normal inside it; on an edge or a vertex the interpolated vertex normals (a spike tip)
        n = np.where((b.min(1) > 1e-3)[:, None], fn[f], np.einsum("jk,jkc->jc", b, vn[Fi[f]]))
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
        near = d > -eps  # outside, or on the surface: start just inside c
        to_c = c - P
        dist = np.linalg.norm(to_c, axis=1)
        u = np.where(near[:, None], n, to_c / np.maximum(dist, 1e-30)[:, None])
        start = np.where(near[:, None], c - eps * n, P)
        a = np.where(near, eps, dist)
        t, hit = ray_hit(V, F, torch.as_tensor(start), torch.as_tensor(-u), max_t=1e6)
        t, ok = t.double().numpy(), hit.numpy() >= 0
        h = np.minimum(0.5 * (a + t), cap)
        move = ok & (near | (a < h))
        P = np.where(move[:, None], c - u * h[:, None], P)
    # a point at a spike or fold can have no usable inward direction: snap what is still outside to the
    # nearest middle of an inward chord from a vertex (points inside the body, one per vertex)
    out = closest_point(V, F, torch.as_tensor(P))[0].numpy() >= 0
    if out.any():
        o = X - eps * vn
        t, hit = ray_hit(V, F, torch.as_tensor(o), torch.as_tensor(-vn), max_t=1e6)
        mids = (o - vn * (0.5 * t.double().numpy())[:, None])[hit.numpy() >= 0]
        if len(mids):
            mids = mids[closest_point(V, F, torch.as_tensor(mids))[0].numpy() < 0]
        if len(mids):
            near = np.linalg.norm(P[out][:, None] - mids[None], axis=-1).argmin(1)
            P[out] = mids[near]
    return P


def parent_anchors(parents, pairs, positions) -> np.ndarray:
    """``(B, 3)`` each bone's joint with its parent (the growth anchor), NaN where there is none.

    Args:
        parents: ``(B,)`` tree. pairs: ``(J, 2)`` joint bone pairs. positions: ``(J, 3)`` joint positions.
    """
    P = _np(parents, np.int64)
    Jp = _np(pairs, np.int64).reshape(-1, 2)
    Jx = _np(positions).reshape(-1, 3)
    out = np.full((len(P), 3), np.nan)
    for (a, b), x in zip(Jp, Jx):
        if P[b] == a:
            out[b] = x
        elif P[a] == b:
            out[a] = x
    return out


# ---------------------------------------------------------------------------------------------------
# bone ends (the lengths of eq. 6)
# ---------------------------------------------------------------------------------------------------


def bone_endpoints(verts, weights, pairs, t_r: float = 0.4, far_fraction: float = 0.1,
                   fallback_count: int = 4, samples: SurfaceSamples | None = None) -> np.ndarray:
    """``(B, 2, N)`` endpoint selection: bone b's two ends are ``E[b, 0] @ X`` and ``E[b, 1] @ X``.

    A bone's length is the distance between its ends ("distance between the coordinates of joint
    pairs"), so the ends are chosen once, on the canonical mesh, and then follow the vertices:
    - two or more joints: the two of its joints farthest apart;
    - one joint (an end bone): that joint and the far end, the mean of the ``far_fraction`` of its
      part's vertices ``I_b`` farthest from the joint;
    - no joint: the means of the lowest and highest ``far_fraction`` of ``I_b`` along its principal axis;
    - no part vertices: both ends at the vertex of largest weight (length 0).

    ``samples``: joints taken over points spread over the surface (:func:`joint_selection`).
    """
    X, W = _bones_in("bone_endpoints", verts, weights)
    P = _np(pairs, np.int64).reshape(-1, 2)
    N, B = W.shape
    Jsel = joint_selection(W, P, t_r, fallback_count, samples)
    jpos = Jsel @ X
    lab = assign_parts(W)
    E = np.zeros((B, 2, N))

    def mean_of(idx: np.ndarray) -> np.ndarray:
        r = np.zeros(N)
        r[idx] = 1.0 / len(idx)
        return r

    for b in range(B):
        mine = [j for j, (a, c) in enumerate(P) if b in (a, c)]
        part = np.flatnonzero(lab == b)
        nfar = max(1, int(round(far_fraction * len(part))))
        if len(mine) >= 2:
            d = np.linalg.norm(jpos[mine][:, None] - jpos[mine][None], axis=-1)
            i, k = np.unravel_index(np.argmax(d), d.shape)
            E[b, 0], E[b, 1] = Jsel[mine[i]], Jsel[mine[k]]
        elif len(part) == 0:
            E[b, 0] = E[b, 1] = mean_of(np.array([int(np.argmax(W[:, b]))]))
        elif len(mine) == 1:
            E[b, 0] = Jsel[mine[0]]
            dist = np.linalg.norm(X[part] - jpos[mine[0]], axis=1)
            E[b, 1] = mean_of(part[np.argsort(-dist, kind="stable")[:nfar]])
        else:
            c = X[part] - X[part].mean(0)
            axis = np.linalg.svd(c, full_matrices=False)[2][0] if len(part) > 1 else np.array([1.0, 0, 0])
            order = np.argsort(c @ axis, kind="stable")
            E[b, 0], E[b, 1] = mean_of(part[order[:nfar]]), mean_of(part[order[-nfar:]])
    return E


# ---------------------------------------------------------------------------------------------------
# joint creation (eq. 7)
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
    :func:`bone_endpoints`) perpendicular to ``e_1 - e_0``; each side becomes a bone
    (centroid, covariance precision), chained on the parent's side first, with a new joint at m.

    Args:
        verts, weights, centers, precisions, parents: as in :func:`s3o_warp.skeleton.edit.grow_skeleton`.
        endpoints: ``(B, 2, N)`` row-normalised endpoint selection matrix.
        bones: ``(B,)`` bool, which bones get a joint (:func:`s3o_warp.skeleton.measures.create_joints`).
        sharpness, min_section_vertices, extents: as in :func:`s3o_warp.skeleton.edit.upsample_skeleton`.

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


__all__ = [
    "SurfaceSamples",
    "bone_endpoints",
    "bone_halves",
    "centre_in_body",
    "gaussian_weights",
    "joint_positions",
    "joint_selection",
    "parent_anchors",
    "split_at_joints",
    "surface_samples",
]
