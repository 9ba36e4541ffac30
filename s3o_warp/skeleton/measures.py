"""Skeleton learning, the M-step of phase 2 (paper 3.3-3.4), as pure functions.

Measurements (this module): per-bone motion from optical flow (eq. 4), motion similarity (eq. 8),
joint positions from skinning weights, bone endpoints and per-frame bone lengths (eq. 6, corrected),
the kinematic tree over the joint graph, the LASR-like virtual-bone baseline, and ``skeleton.json``.
Edits (:mod:`s3o_warp.skeleton.edit`, re-exported here): bone shifting (eq. 5), growth, upsampling,
joint creation (eq. 7), merging (eq. 9) and :func:`remap_bones`, the model surgery that applies an edit
to an ``S3OModel`` and its Adam optimiser without a jump in the posed mesh.

Notation (paper Table 4): ``X^0 = M_c`` canonical vertices ``(N, 3)`` (object frame); ``W`` skinning
weights ``(N, B)``; bone b has centre ``C_b``, precision ``Q_b`` and a length; a joint ``J_ij`` joins
bones i and j at a 3D position; ``F^{B,t}`` ``(B, 2)`` bone motion in the image between frames t and
t+1 (crop pixels); ``V^t`` ``(N,)`` vertex visibility at frame t; ``I_b`` the vertices whose argmax
weight is b. Every threshold is a keyword argument whose default is the paper's value where it gives
one.

A typical M-step (the fit loop owns the order and the schedule; ``apply = lambda e:
apply_edit(model, optimizer, e)``, and after every edit W, C, Q and parents are re-read)::

    ident = [[(b, 1.0)] for b in range(B)]                          # eq. 5, every M-step
    remap_bones(model, opt, ident, shift_bones(X, W, C), model.bone_quat, model.bone_log_scales)
    apply(grow_skeleton(X, W, C, Q, parents, ref_extents))          # before e1 (keep edit.extents)
    apply(upsample_skeleton(X, W, C, Q, parents))                   # once, at e1
    F, ok = bone_flow(verts_cam, K_crop, flow_fwd, visible, W)      # after e1
    apply(merge_bones(motion_similarity(F, ok), W, C, Q, parents, t_o))
    E = bone_endpoints(X, W, tree_joints(parents))
    apply(prune_short_bones(bone_lengths(E, X), min_length, W, C, Q, parents))  # not in the paper
    E = bone_endpoints(X, W, tree_joints(parents))
    L = bone_lengths_per_frame(E, model.posed_object(frames, W))
    bend = end bones whose halves' unexplained_motion(bone_flow(..., predicted=...)) > t_u  # not in the paper
    apply(split_at_joints(X, W, C, Q, parents, E, create_joints(L, t_d, min_length) | bend))
    pairs = tree_joints(parents); J = joint_positions(X, W, pairs); lengths = bone_lengths(E, X)
"""

from __future__ import annotations

import logging
from collections import deque
from typing import NamedTuple

import numpy as np
import torch

from s3o_warp.skeleton.edit import (
    DEFAULT_SHARPNESS,
    SkeletonEdit,
    _bones_in,
    _check,
    _np,
    apply_edit,
    assign_parts,
    bone_halves,
    children_of,
    fit_bones_to_parts,
    grow_skeleton,
    merge_bones,
    part_extents,
    precision_from_points,
    precision_to_quat_scales,
    prune_short_bones,
    remap_bones,
    shift_bones,
    split_at_joints,
    tree_joints,
    upsample_skeleton,
)

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------------
# bone motion from optical flow (eq. 4)
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
    from s3o_warp.geometry import project

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

    For each pair ``(p, d)`` of columns (the two halves of one bone's part, :func:`s3o_warp.skeleton.measures.bone_halves`)
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
# joints, endpoints, lengths
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


def size_of(verts) -> float:
    """The bbox diagonal of ``(N, 3)`` canonical vertices: the unit of the M-step's relative lengths
    (``s3o_warp.skeleton.mstep.JOINT_DEPTH``, ``MIN_BONE_LENGTH``)."""
    X = _np(verts)
    return float(np.linalg.norm(X.max(0) - X.min(0)))


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
    from s3o_warp.kernels.sdf import closest_point, ray_hit

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


def bone_lengths(endpoints, verts) -> np.ndarray:
    """Bone lengths ``|E[b,1] X - E[b,0] X|``: ``(B,)`` for ``(N, 3)`` verts, ``(T, B)`` for posed ``(T, N, 3)``.

    Per frame, the length of bone b is the distance between its two endpoints (:func:`bone_endpoints`)
    carried by the posed vertices; a joint's vertex set moves with the blend of both its bones, so a
    bone whose region bends or stretches changes length, a rigidly moving one does not.
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
    of median length 0 never qualify. Apply the result with :func:`split_at_joints`.

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
# kinematic tree
# ---------------------------------------------------------------------------------------------------


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
# LASR-like baseline
# ---------------------------------------------------------------------------------------------------


def virtual_bones(verts, num_bones: int, seed: int = 0, sharpness: float = DEFAULT_SHARPNESS,
                  iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Virtual bones (LASR baseline): k-means centres over the surface, isotropic precisions.

    ``scipy.cluster.vq.kmeans2`` (k-means++ init, ``seed``-ed generator); each bone's precision is
    ``Q = sharpness / sigma^2 I`` with ``sigma^2`` the mean per-axis squared distance of its cluster
    (the vertices nearest the final centre) from the centre; clusters of fewer than 2 vertices get the
    mean over the other clusters.

    Args:
        verts: ``(N, 3)`` canonical vertices.
        num_bones: B (at most N).
        seed: random seed; the same seed gives the same bones.
        sharpness: precision scale.
        iterations: k-means iterations.

    Returns:
        ``centers`` ``(B, 3)`` and ``precisions`` ``(B, 3, 3)``, float64.
    """
    from scipy.cluster.vq import kmeans2

    X = _np(verts)
    _check("virtual_bones", "verts", X, (None, 3))
    if not 1 <= num_bones <= len(X):
        raise ValueError(f"virtual_bones(): num_bones must be in [1, {len(X)}], got {num_bones}")
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # scipy warns about empty clusters; handled below
        cen, _ = kmeans2(X, num_bones, iter=iterations, minit="++", seed=np.random.default_rng(seed))
    lab = np.argmin(((X[:, None] - cen[None]) ** 2).sum(-1), 1)  # clusters of the final centres
    var = np.full(num_bones, np.nan)
    for b in range(num_bones):
        p = X[lab == b]
        if len(p) >= 2:
            var[b] = ((p - cen[b]) ** 2).sum(1).mean() / 3
    fill = np.nanmean(var) if np.isfinite(var).any() else 1.0
    var = np.where(np.isfinite(var) & (var > 1e-12), var, fill)
    return cen.astype(np.float64), np.eye(3)[None] * (sharpness / var)[:, None, None]


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
    "DEFAULT_SHARPNESS",
    "SkeletonEdit",
    "SurfaceSamples",
    "apply_edit",
    "assign_parts",
    "bone_endpoints",
    "bone_halves",
    "bone_flow",
    "bone_lengths",
    "bone_lengths_per_frame",
    "children_of",
    "create_joints",
    "fit_bones_to_parts",
    "gaussian_weights",
    "grow_skeleton",
    "joint_positions",
    "centre_in_body",
    "joint_selection",
    "kinematic_tree",
    "merge_bones",
    "motion_similarity",
    "parent_anchors",
    "part_extents",
    "precision_from_points",
    "precision_to_quat_scales",
    "prune_short_bones",
    "remap_bones",
    "shift_bones",
    "size_of",
    "skeleton_json",
    "split_at_joints",
    "surface_samples",
    "tree_joints",
    "unexplained_motion",
    "upsample_skeleton",
    "virtual_bones",
]
