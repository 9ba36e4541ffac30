"""The E-step's objective (paper 3.3, eq. 9 and the regularisers) as a pure function of the model, the frames and
the settings: :func:`motion_terms` returns named terms, each ``(weight, value)``; the loop sums them.

Terms: silhouette (soft rasteriser), colour (L1), mask coverage (not in the paper: uncovered mask pixels pull
their nearest projected vertex), optical flow (rendered vertex motion against the observed flow, weighted by
forward-backward confidence), rigidity (dynamic, eq. 1-2 as corrected in docs/method.md, or ARAP for the
ablation), joint attachment (not in the paper: each joint lands in one place under both its bones), in the
joint phase the Laplacian (eq. 17, of the change from a reference shape) and symmetry (eq. 16), temporal
smoothness of root and bone motion, and a penalty on bone translations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from s3o_warp import interrupt
from s3o_warp.config import MotionConfig
from s3o_warp.data.store import FitData
from s3o_warp.geometry import project
from s3o_warp.model import S3OModel
from s3o_warp.motion import losses as L
from s3o_warp.ops import (
    arap_loss,
    dynamic_rigidity_loss,
    interpolate,
    laplacian_loss,
    rasterize,
    soft_silhouette,
    symmetry_loss,
)

COVER_PIXELS = 256
"""Uncovered mask pixels sampled per frame for the coverage loss (0 = all)."""


@dataclass
class TermContext:
    """What the terms need besides the model and the frames; the loop renews it when the mesh or skeleton changes.

    Attributes:
        edges: (E, 2) int64 mesh edges of the canonical mesh (rigidity).
        lap_ref: (V, 3) float32 reference shape of the Laplacian term (the mesh at the phase's start and after
            each even resampling).
        sym_plane: (normal (3,) tensor, offset) of the lift's symmetry plane, object frame.
        size: the object's size (the coarse mesh's bounding-box diagonal), to make the joint term unitless.
        joints: ((J, 2) int64 bone pairs, (J, 3) float32 rest positions) of the kinematic tree's joints.
        frame_pairs: (T - 1,) bool, consecutive frames of one video (several videos; None: all of them).
        motion_pairs: the same for the rows of the bone motion (None: all of them).
    """

    edges: torch.Tensor
    lap_ref: torch.Tensor
    sym_plane: tuple
    size: float
    joints: tuple[torch.Tensor, torch.Tensor] | None = None
    frame_pairs: torch.Tensor | None = None
    motion_pairs: torch.Tensor | None = None


def decayed_sigma(start: float, final: float, step: int, steps: int) -> float:
    """Soft-silhouette sigma at ``step`` of a phase of ``steps``: geometric decay from ``start`` to ``final``."""
    n = max(1, steps - 1)
    return float(start * (final / start) ** min(1.0, step / n))


def motion_terms(model: S3OModel, data: FitData, frames: torch.Tensor, mc: MotionConfig, *, joint_phase: bool,
                 sigma: float, ctx: TermContext) -> tuple[dict, torch.Tensor, torch.Tensor]:
    """The E-step's terms on a window of consecutive ``frames`` (T,) int64.

    Returns ``(terms, sil, mask)``: ``terms[name] = (weight, value)`` with scalar values; the soft silhouette and
    the crop masks, both (T, S, S) float32. ``joint_phase`` adds the shape terms (Laplacian, symmetry): in the
    warm-up the mesh is frozen.
    """
    m, d = model, data
    S = d.crop_size
    W = m.skinning()
    verts = m(frames, weights=W)
    K = m.intrinsics_crop(frames)
    sil = soft_silhouette(verts, m.faces, K, (S, S), sigma=sigma)
    mask = d.masks[frames]
    fw = d.frame_weight[frames] if d.frame_weight is not None else None
    terms = {"sil": (mc.w_sil, L.silhouette_loss(sil, mask, fw))}
    face_index, bary, _depth = rasterize(verts, m.faces, K, (S, S))
    fg = (face_index >= 0).float()
    if mc.w_color > 0:
        col = interpolate(m.colors(), m.faces, face_index, bary)
        terms["color"] = (mc.w_color, L.color_loss(col, d.images[frames], fg * mask))
    if mc.w_cover > 0:
        uncovered = (mask > 0.5) & (face_index < 0)
        terms["cover"] = (mc.w_cover, L.coverage_loss(project(verts, K), uncovered, COVER_PIXELS))
    if mc.w_flow > 0 and len(frames) > 1:
        vflow = L.vertex_flow_crop(verts, K)
        rflow = interpolate(vflow, m.faces, face_index[:-1], bary[:-1])
        pairs = frames[:-1]
        valid = fg[:-1] * mask[:-1]
        terms["flow"] = (mc.w_flow, L.flow_loss(rflow, d.flow_fwd[pairs], d.conf_fwd[pairs], valid))
    if len(frames) > 1 and mc.rigidity != "none" and mc.w_rigid > 0:
        if mc.rigidity == "dynamic":
            terms["rigid"] = (mc.w_rigid, dynamic_rigidity_loss(verts, ctx.edges, W.detach()))
        else:
            terms["rigid"] = (mc.w_rigid, arap_loss(verts, ctx.edges))
    if mc.w_joint > 0 and ctx.joints is not None and len(ctx.joints[0]):
        J, P = ctx.joints
        terms["joint"] = (mc.w_joint, L.joint_attachment_loss(m.bone_rt(frames), J, P, ctx.size))
    if joint_phase:
        terms["lap"] = (mc.w_lap, laplacian_loss(m.verts - ctx.lap_ref, m.faces))
        terms["sym"] = (mc.w_sym, symmetry_loss(m.verts, ctx.sym_plane))
    fp, mp = ctx.frame_pairs, ctx.motion_pairs
    smooth = (
        L.temporal_smoothness(m.root_aa, fp)
        + L.temporal_smoothness(m.root_t, fp)
        + L.temporal_smoothness(m.bone_aa, mp)
        + L.temporal_smoothness(m.bone_t, mp)
    )
    terms["smooth"] = (mc.w_smooth, smooth)
    terms["bone_reg"] = (mc.w_bone_reg, (m.bone_t[m.motion_of[frames]] ** 2).mean())
    return terms, sil, mask


def total(terms: dict) -> torch.Tensor:
    """The weighted sum of ``terms``."""
    return sum(w * v for w, v in terms.values())


@torch.no_grad()
def mean_terms(terms_of, num_frames: int, batch_frames: int, device, span: tuple[int, int] | None = None
               ) -> dict[str, float]:
    """Every weighted term of ``terms_of(frames)`` averaged over windows that cover every frame (of ``span``,
    ``(start, stop)``: one video's) with no step taken; consecutive windows share a frame, so every frame pair is
    seen. A stop request (:mod:`s3o_warp.interrupt`) ends it between windows (it changes nothing: the caller can
    score again)."""
    a, b = span or (0, num_frames)
    n = min(batch_frames, b - a)
    starts = list(range(a, b - n + 1, max(n - 1, 1)))
    if starts[-1] != b - n:
        starts.append(b - n)
    acc: dict[str, list[float]] = {}
    for s in starts:
        interrupt.check("the scoring of a camera hypothesis")
        terms, _, _ = terms_of(torch.arange(s, s + n, device=device))
        for k, (w, v) in terms.items():
            acc.setdefault(k, []).append(float(w * v))
    return {k: float(np.mean(v)) for k, v in acc.items()}


@torch.no_grad()
def flow_by_gap(model: S3OModel, data: FitData, batch_frames: int, span: tuple[int, int] | None = None
                ) -> dict[int, float]:
    """The flow term (eq. 11, unweighted) over every pair (t, t + g) of every gap g the data holds: consecutive
    pairs and :attr:`FitData.long_flow`'s. Frame t is rendered, both frames posed, and the projected displacement
    of the surface seen at each pixel of frame t is compared with the observed flow there. Over a gap of g frames
    a wrong turn rate moves the body by g times its error, so the long gaps tell rates apart that consecutive
    pairs cannot (``docs/method.md``, camera hypotheses). ``span`` ``(start, stop)``: the pairs of those frames only
    (one video's). A stop request ends it between batches."""
    m, d, S = model, data, data.crop_size
    a, T = span or (0, data.num_frames)
    W = m.skinning()
    dev = m.verts.device
    stores = {1: (d.flow_fwd, d.conf_fwd), **(d.long_flow or {})}
    num, den = dict.fromkeys(stores, 0.0), dict.fromkeys(stores, 0.0)
    for s in range(a, T - 1, batch_frames):  # each frame t rendered once, for all its gaps
        interrupt.check("the flow score of a camera hypothesis")
        t = torch.arange(s, min(s + batch_frames, T - 1), device=dev)
        vt, Kt = m(t, weights=W), m.intrinsics_crop(t)
        fi, bary, _ = rasterize(vt, m.faces, Kt, (S, S))
        pt, seen = project(vt, Kt), (fi >= 0).float() * d.masks[t]
        for g, (flow, conf) in stores.items():
            k = int((t + g < T).sum())  # t ascending: the first k frames have a partner g later
            if k == 0:
                continue
            u = t[:k] + g
            disp = project(m(u, weights=W), m.intrinsics_crop(u)) - pt[:k]
            rendered = interpolate(disp, m.faces, fi[:k], bary[:k])
            w = conf[t[:k]] * seen[:k]
            num[g] += float((w * (rendered - flow[t[:k]]).norm(dim=-1)).sum())
            den[g] += float(w.sum())
    return {g: num[g] / max(den[g], 1.0) for g in sorted(stores)}


@torch.no_grad()
def hard_iou(model: S3OModel, data: FitData, batch_frames: int) -> float:
    """Mean over all frames of the hard-render IoU with the crop masks (what the metrics measure)."""
    m, S = model, data.crop_size
    W = m.skinning()
    ious = []
    for s in range(0, data.num_frames, batch_frames):
        fr = torch.arange(s, min(s + batch_frames, data.num_frames), device=m.verts.device)
        fi, _, _ = rasterize(m(fr, weights=W), m.faces, m.intrinsics_crop(fr), (S, S))
        ious.append(L.soft_iou((fi >= 0).float(), data.masks[fr]))
    return float(torch.cat(ious).mean())
