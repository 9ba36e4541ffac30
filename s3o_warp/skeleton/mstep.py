"""The M-step schedule (paper 3.4, Algorithm 1) and its tuning constants: called by the fit after each epoch
of the joint phase, it adapts the skeleton to the current mesh and motion. Before epoch ``e1`` it shifts the bones
(eq. 5) and grows stretched end parts; at ``e1`` it upsamples the skeleton once; after ``e1`` comes the physically
constrained refinement: merge neighbouring bones whose motion directions in the flow between the crops agree in
every frame (eqs. 8-9, similarity > t_o; each merge step logs every bone's similarity to its parent), merge bones
shorter than :data:`MIN_BONE_LENGTH` into their parents (not in the paper), and split in two, at a new joint, the
bones whose length varies over the frames (eqs. 6-7, corrected) and (not in the paper) those whose two halves move
in a way one rigid bone does not reproduce (:func:`end_bone_bending`). Every edit is applied with
:func:`s3o_warp.skeleton.remap.apply_edit`, which carries motion and optimiser state over so that the loss does
not jump, and the joints are then re-derived from the kinematic tree and placed by t_r (:func:`refresh_joints`).
The thresholds a user sets are in ``SkeletonConfig`` (t_o, t_d, t_r, t_u, e1, max_bones); the constants below are
the M-step's own, lengths and depths as fractions of the canonical mesh's bbox diagonal
(:func:`s3o_warp.skeleton.measures.size_of`), flows in crop pixels. The LASR-like baseline's k-means bones
(:func:`virtual_bones`), which replace the M-step, are set up here too.
"""

from __future__ import annotations

import logging
import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.cluster.vq import kmeans2

from s3o_warp.motion.losses import vertex_flow_crop
from s3o_warp.ops import vertex_visibility
from s3o_warp.skeleton.edit import (
    DEFAULT_SHARPNESS,
    SkeletonEdit,
    grow_skeleton,
    merge_bones,
    precision_to_quat_scales,
    prune_short_bones,
    shift_bones,
    upsample_skeleton,
)
from s3o_warp.skeleton.joints import (
    SurfaceSamples,
    bone_endpoints,
    bone_halves,
    centre_in_body,
    joint_positions,
    parent_anchors,
    split_at_joints,
    surface_samples,
)
from s3o_warp.skeleton.measures import (
    _check,
    _np,
    bone_flow,
    bone_lengths,
    bone_lengths_per_frame,
    create_joints,
    motion_similarity,
    part_extents,
    size_of,
    tree_joints,
    unexplained_motion,
)
from s3o_warp.skeleton.remap import apply_edit, remap_bones

log = logging.getLogger(__name__)

JOINT_SAMPLES = 4
"""Not in the paper: the joints (t_r) and the bone ends of eq. 6 are taken over points spread over the canonical
surface, each face cut into JOINT_SAMPLES**2 small triangles, with the Gaussian bones' weights there, instead of
over the vertices alone (1, the paper). On a coarse mesh the band where two bones' weights both reach t_r often
lies between a thin leg's vertices."""
JOINT_DEPTH = 0.03
"""Deepest a joint is moved below the surface when it is centred in the body (:func:`refresh_joints`)."""
MIN_BONE_LENGTH = 0.015
"""Not in the paper: after each merge, inner bones shorter than this (and bones that own no vertex) are merged into
their parent, and joint creation never leaves a half shorter than it (0 = the paper: no limit; without it, hips and
shoulders collect knots of ever shorter bones). Short end bones (tail tips, ears, hooves) are kept."""
FAR_FRACTION = 0.1
"""Bone ends of a one-joint bone: the far end is the mean of its farthest fraction of part vertices."""
GROWTH_FACTOR = 2.0
"""Grow an end part whose extent passed this many times its initial extent (paper: 2)."""
GROWTH_SECTIONS = 2
"""Sections a grown end part is split into."""
SHARPNESS = 0.6667
"""Precision of a new bone = SHARPNESS / variance of its section's vertices (2/3 to four digits)."""
MIN_SECTION_VERTICES = 4
"""Growth, upsampling and joint creation split a bone only when each new bone would own at least this many
vertices (its part: the vertices it weighs most)."""
MERGE_TEMPERATURE = 1.0
"""Temperature of the log-space softmax of the merge weights (sum of skinning weights per bone; 1 = the paper)."""
MIN_VISIBLE = 0.1
"""Bone flow: skip frames where less than this fraction of a bone's weight is visible."""
MIN_MASS = 3.0
"""Bone flow: skip frames where a bone's visible weight mass (in vertices) is below this."""
MIN_FLOW = 0.5
"""Motion similarity: frames where both bones move less than this (crop pixels) say nothing about direction."""
MIN_FRAMES = 2
"""Motion similarity: bone pairs with fewer usable frames are never merged."""
MIN_FRAMES_FRACTION = 0.25
"""Not in the paper: nor are pairs compared on fewer than this fraction of the frame pairs (the larger of the two
minimums applies; 0 = MIN_FRAMES alone). "Moves together in every frame" read off a few frames is no evidence: on
the 120-degree Fox (seed 1) a far-side hind thigh seen moving in 6 of 47 frame pairs agreed with its shin there
(0.957) and the two merged into one bone with no knee; the other bones are seen in 21-45."""


@dataclass
class SkeletonState:
    """What the M-step keeps between epochs (checkpointed with the model)."""

    parents: np.ndarray  # (B,) kinematic tree, -1 root
    joints: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))  # (J, 2) bone pairs
    joint_positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (J, 3) object frame
    extents: np.ndarray | None = None  # (B,) growth reference extents
    history: list = field(default_factory=list)  # one dict per M-step: epoch, operation, bone counts

    def to_dict(self) -> dict:
        return {
            "parents": self.parents.tolist(),
            "joints": self.joints.tolist(),
            "joint_positions": self.joint_positions.tolist(),
            "extents": None if self.extents is None else self.extents.tolist(),
            "history": self.history,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "SkeletonState":
        return cls(
            parents=np.asarray(d["parents"], np.int64),
            joints=np.asarray(d["joints"], np.int64).reshape(-1, 2),
            joint_positions=np.asarray(d["joint_positions"], np.float64).reshape(-1, 3),
            extents=None if d["extents"] is None else np.asarray(d["extents"], np.float64),
            history=list(d["history"]),
        )


def _xw(model):
    X = model.verts.detach().cpu().double().numpy()
    W = model.skinning().detach().cpu().double().numpy()
    return X, W


def _q(model) -> np.ndarray:
    return model.precisions().detach().cpu().double().numpy()


def joint_samples(model) -> SurfaceSamples | None:
    """The points over the canonical surface the joints are taken over (:data:`JOINT_SAMPLES`), or None (the
    vertices)."""
    return surface_samples(model.verts.detach().cpu().double().numpy(), model.faces.detach().cpu().numpy(),
                           model.bone_centers.detach().cpu().double().numpy(), _q(model), JOINT_SAMPLES)


def refresh_joints(model, state: SkeletonState, sc) -> None:
    """Joints = the kinematic tree's (parent, child) pairs, placed at the mean of the shared vertices
    (``sc.t_r``), then moved into the body (:func:`s3o_warp.skeleton.joints.centre_in_body`; not in the paper): to the
    middle of a thin limb's cross-section, at most :data:`JOINT_DEPTH` below the surface of a thick part (the mean
    sits on the surface when the shared vertices are on one side of a limb). ``sc`` is the run's
    ``SkeletonConfig``."""
    X, W = _xw(model)
    state.joints = tree_joints(state.parents)
    if not len(state.joints):
        state.joint_positions = np.zeros((0, 3))
        return
    J = joint_positions(X, W, state.joints, t_r=sc.t_r, samples=joint_samples(model))
    state.joint_positions = centre_in_body(J, X, model.faces.detach().cpu().numpy(), max_depth=JOINT_DEPTH)


def prune_empty_bones(model, opt, state: SkeletonState, sc, epoch: int = -1) -> bool:
    """Merge the bones that own no vertex into their parents (:func:`s3o_warp.skeleton.edit.prune_short_bones` with
    no length limit), carrying motion and optimiser state over; the fit's last step, not in the paper: such a bone
    moves nothing, and its joints fall back to far-apart borders (a leg's top joint at the tail's base).
    ``epoch`` only labels the history entry and the log line (-1: after the last epoch). Returns whether the
    skeleton changed."""
    if not len(state.joints):
        return False
    return _apply(model, opt, state, _prune_edit(model, state, sc, 0.0), "prune empty (end)", epoch, sc)


def _prune_edit(model, state: SkeletonState, sc, min_length: float):
    """:func:`s3o_warp.skeleton.edit.prune_short_bones` on the model's canonical bone lengths; ``min_length`` a fraction
    of the mesh's size."""
    X, W = _xw(model)
    C, Q = model.bone_centers.detach().cpu().double().numpy(), _q(model)
    L = bone_lengths(bone_endpoints(X, W, state.joints, t_r=sc.t_r, far_fraction=FAR_FRACTION,
                                    samples=joint_samples(model)), X)
    return prune_short_bones(L, min_length * size_of(X), W, C, Q, state.parents, extents=state.extents)


def _apply(model, opt, state: SkeletonState, edit, what: str, epoch: int, sc) -> bool:
    if not edit.changed:
        return False
    b0 = model.num_bones
    apply_edit(model, opt, edit)
    state.parents = np.asarray(edit.parents, np.int64)
    if edit.extents is not None:
        state.extents = np.asarray(edit.extents, np.float64)
    refresh_joints(model, state, sc)
    state.history.append({"epoch": epoch, "operation": what, "bones_before": b0, "bones_after": model.num_bones})
    log.info("M-step epoch %d: %s, %d -> %d bones", epoch, what, b0, model.num_bones)
    return True


def merge_min_frames(num_frames: int) -> int:
    """Fewest frame pairs a bone pair must be compared on before it may merge: the larger of :data:`MIN_FRAMES`
    and :data:`MIN_FRAMES_FRACTION` of the ``num_frames - 1`` pairs."""
    return max(MIN_FRAMES, int(math.ceil(MIN_FRAMES_FRACTION * max(num_frames - 1, 0) - 1e-9)))


def _pair_windows(model, T: int, batch_frames: int):
    """Windows of consecutive frames, each starting at the previous one's last frame, so that together they hold
    every frame pair (t, t+1) once."""
    chunk = max(2, batch_frames)
    for s in range(0, T - 1, chunk - 1):
        fr = torch.arange(s, min(s + chunk, T), device=model.verts.device)
        if len(fr) < 2:
            break
        yield fr


@torch.no_grad()
def bone_motion_similarity(model, data, cfg) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 4 + 8: per-bone flow over all frames (visible vertices only), min-over-frames cosine ``(B, B)``,
    and the ``(B, B)`` counts of frames each pair was compared on (:func:`s3o_warp.skeleton.measures.motion_similarity`)."""
    W = model.skinning()
    FB, valid = [], []
    for fr in _pair_windows(model, data.num_frames, cfg.motion.batch_frames):
        v = model(fr, weights=W)
        K = model.intrinsics_crop(fr)
        vis = vertex_visibility(v, model.faces)
        fb, ok = bone_flow(v, K, data.flow_fwd[fr[:-1]], vis, W, conf=data.conf_fwd[fr[:-1]],
                           min_visible=MIN_VISIBLE, min_mass=MIN_MASS)
        FB.append(fb)
        valid.append(ok)
    FB = torch.cat(FB, 0)
    valid = torch.cat(valid, 0)
    S, N = motion_similarity(FB, valid, min_flow=MIN_FLOW, min_frames=MIN_FRAMES, return_frames=True)
    return S.cpu().double().numpy(), N.cpu().numpy()


@torch.no_grad()
def bone_length_variation(model, data, state: SkeletonState, cfg) -> tuple[np.ndarray, np.ndarray]:
    """Which bones' lengths vary over frames (eq. 6 corrected), ``(B,)`` bool, and the endpoints used."""
    sc = cfg.skeleton
    X, W = _xw(model)
    E = bone_endpoints(X, W, state.joints, t_r=sc.t_r, far_fraction=FAR_FRACTION,
                       samples=joint_samples(model))
    lengths = []
    Wt = model.skinning()
    for s in range(0, data.num_frames, cfg.motion.batch_frames):
        fr = torch.arange(s, min(s + cfg.motion.batch_frames, data.num_frames), device=model.verts.device)
        lengths.append(bone_lengths_per_frame(E, model.posed_object(fr, weights=Wt).cpu().double().numpy()))
    return create_joints(np.concatenate(lengths, 0), t_d=sc.t_d, min_length=MIN_BONE_LENGTH * size_of(X)), E


@torch.no_grad()
def end_bone_bending(model, data, state: SkeletonState, E: np.ndarray, cfg) -> np.ndarray:
    """Per bone, how much of the relative motion of its part's two halves the fit leaves unexplained
    (:func:`s3o_warp.skeleton.measures.unexplained_motion`), ``(B,)``; NaN for bones that have no joint, are shorter than
    twice :data:`MIN_BONE_LENGTH`, cannot be cut or are seen in too few frames.

    Not in the paper: an end bone's length runs from its joint to its far end, which both move with the bone,
    so eq. 6 never gives it a joint; a knee inside it shows in the flow instead, as two halves that the one
    rigid bone cannot move as the video does. An inner bone's halves are cut half way between its two farthest
    joints (eq. 6's ends).
    """
    sc = cfg.skeleton
    X, W = _xw(model)
    B = W.shape[1]
    out = np.full(B, np.nan)
    if not len(state.joints):
        return out
    count = np.bincount(np.asarray(state.joints).ravel(), minlength=B)
    ends = (count >= 1) & (bone_lengths(E, X) >= 2.0 * MIN_BONE_LENGTH * size_of(X))
    if not ends.any():
        return out
    C = model.bone_centers.detach().cpu().double().numpy()
    bones, W2 = bone_halves(X, W, C, state.parents, E, ends, min_section_vertices=MIN_SECTION_VERTICES)
    if not len(bones):
        return out
    W2 = torch.as_tensor(W2, dtype=torch.float32, device=model.verts.device)
    Wt = model.skinning()
    FB, GB, valid = [], [], []
    for fr in _pair_windows(model, data.num_frames, cfg.motion.batch_frames):
        v = model(fr, weights=Wt)
        K = model.intrinsics_crop(fr)
        fb, ok, gb = bone_flow(v, K, data.flow_fwd[fr[:-1]], vertex_visibility(v, model.faces), W2,
                               conf=data.conf_fwd[fr[:-1]], min_visible=MIN_VISIBLE, min_mass=MIN_MASS,
                               predicted=vertex_flow_crop(v, K))
        FB.append(fb)
        GB.append(gb)
        valid.append(ok)
    r, n = unexplained_motion(torch.cat(FB), torch.cat(GB), torch.cat(valid),
                              np.arange(2 * len(bones)).reshape(-1, 2), min_flow=MIN_FLOW,
                              min_frames=merge_min_frames(data.num_frames))
    out[bones] = r
    log.info("M-step: unexplained motion of the bones' halves: %s (t_u %.3g)",
             " ".join(f"{b}:{x:.3f}/{k}" for b, x, k in zip(bones.tolist(), r, n.tolist())), sc.t_u)
    return out


def m_step(model, opt, data, cfg, state: SkeletonState, epoch: int) -> bool:
    """One M-step after epoch ``epoch`` of the joint phase; returns whether the skeleton changed."""
    sc = cfg.skeleton
    if sc.method != "s3o":
        return False
    changed = False
    X, W = _xw(model)
    C = model.bone_centers.detach().cpu().double().numpy()
    Q = _q(model)
    if state.extents is None:
        state.extents = part_extents(X, W)
    if epoch < sc.e1:
        # bone shifting (eq. 5): centres to their parts' centroids, motion carried over exactly
        C2 = shift_bones(X, W, C)
        if np.abs(C2 - C).max() > 1e-9:
            edit = SkeletonEdit(centers=C2, precisions=Q, parents=state.parents.copy(),
                                sources=[[(b, 1.0)] for b in range(len(C))],
                                kept=np.zeros(len(C), bool), extents=state.extents)
            changed |= _apply(model, opt, state, edit, "shift", epoch, sc)
            X, W = _xw(model)
            C, Q = model.bone_centers.detach().cpu().double().numpy(), _q(model)
        anchors = parent_anchors(state.parents, state.joints, state.joint_positions) if len(state.joints) else None
        edit = grow_skeleton(X, W, C, Q, state.parents, state.extents, growth_factor=GROWTH_FACTOR,
                             sections=GROWTH_SECTIONS, anchors=anchors, sharpness=SHARPNESS,
                             min_section_vertices=MIN_SECTION_VERTICES)
        if model.num_bones + (edit.num_bones - model.num_bones) <= sc.max_bones:
            changed |= _apply(model, opt, state, edit, "grow", epoch, sc)
    elif epoch == sc.e1:
        edit = upsample_skeleton(X, W, C, Q, state.parents, sharpness=SHARPNESS, extents=state.extents,
                                 min_section_vertices=MIN_SECTION_VERTICES)
        if edit.num_bones <= sc.max_bones:
            changed |= _apply(model, opt, state, edit, "upsample", epoch, sc)
    else:
        S, N = bone_motion_similarity(model, data, cfg)
        kid = np.flatnonzero(state.parents >= 0)
        few = merge_min_frames(data.num_frames)
        if len(kid):
            par = state.parents[kid]
            short = (N[kid, par] < few) & (S[kid, par] > sc.t_o)
            if short.any():
                log.info("M-step epoch %d: bones %s agree with their parents %s (%s) on only %s of %d frame pairs "
                         "(fewer than %d): not merged", epoch, kid[short].tolist(),
                         par[short].tolist(), " ".join(f"{x:.3f}" for x in S[kid, par][short]),
                         N[kid, par][short].tolist(), data.num_frames - 1, few)
        S = np.where(N >= few, S, -np.inf)
        np.fill_diagonal(S, 1.0)
        if len(kid):  # what t_o is compared with: the motion similarity of each bone and its parent
            s_pc = S[kid, state.parents[kid]]
            fin = s_pc[np.isfinite(s_pc)]
            log.info("M-step epoch %d: motion similarity of the %d parent-child pairs: %s (%d finite), %d above t_o %.3g",
                     epoch, len(kid), " ".join(f"{x:.3f}" for x in np.sort(fin)[::-1]), len(fin),
                     int((fin > sc.t_o).sum()), sc.t_o)
        edit = merge_bones(S, W, C, Q, state.parents, t_o=sc.t_o, temperature=MERGE_TEMPERATURE,
                           extents=state.extents)
        changed |= _apply(model, opt, state, edit, "merge", epoch, sc)
        if MIN_BONE_LENGTH > 0 and len(state.joints):
            changed |= _apply(model, opt, state, _prune_edit(model, state, sc, MIN_BONE_LENGTH), "prune", epoch, sc)
        if len(state.joints):
            split, E = bone_length_variation(model, data, state, cfg)
            bend = end_bone_bending(model, data, state, E, cfg) > sc.t_u  # not in the paper: a knee inside a bone
            if bend.any():
                log.info("M-step epoch %d: bones %s bend inside (unexplained motion > t_u %.3g)", epoch,
                         np.flatnonzero(bend).tolist(), sc.t_u)
            split = split | bend
            if split.any() and model.num_bones + int(split.sum()) <= sc.max_bones:
                X, W = _xw(model)
                C, Q = model.bone_centers.detach().cpu().double().numpy(), _q(model)
                edit = split_at_joints(X, W, C, Q, state.parents, E, split, sharpness=SHARPNESS,
                                       extents=state.extents, min_section_vertices=MIN_SECTION_VERTICES)
                changed |= _apply(model, opt, state, edit, "joint", epoch, sc)
    if not changed:
        state.history.append({"epoch": epoch, "operation": "none", "bones_before": model.num_bones,
                              "bones_after": model.num_bones})
    return changed


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
    X = _np(verts)
    _check("virtual_bones", "verts", X, (None, 3))
    if not 1 <= num_bones <= len(X):
        raise ValueError(f"virtual_bones(): num_bones must be in [1, {len(X)}], got {num_bones}")
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


def virtual_bones_init(model, cfg) -> np.ndarray:
    """The LASR-like baseline: k-means bones over the canonical surface, a flat tree (all children of bone 0)."""
    X = model.verts.detach().cpu().double().numpy()
    C, Q = virtual_bones(X, cfg.skeleton.virtual_bones, seed=cfg.seed)
    q, s = precision_to_quat_scales(Q)
    dt = dict(dtype=model.bone_centers.dtype, device=model.bone_centers.device)
    remap_bones(model, None, [[(0, 1.0)] for _ in range(len(C))], torch.as_tensor(C, **dt),
                torch.as_tensor(q, **dt), torch.as_tensor(s, **dt))
    parents = np.zeros(len(C), np.int64)
    parents[0] = -1
    return parents
