"""Phase 1 (paper 3.2): the coarse model, and the coarse fit's objective.

:func:`coarse_model` picks the canonical frame, takes its 2D skeleton (:mod:`s3o_warp.coarse.skeleton2d`), lifts it
to ellipsoids, their union mesh and Gaussian bones (:mod:`s3o_warp.coarse.lift`) and returns the model's start. The
fit loop then fits the shape to the canonical frame with :func:`coarse_terms` (silhouette, part silhouettes,
symmetry, Laplacian) and moves each bone onto its part with :func:`refit_bones_to_parts`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import torch

from s3o_warp.coarse import lift, skeleton2d
from s3o_warp.config import CoarseConfig, Config
from s3o_warp.data.store import FitData
from s3o_warp.model import ModelInit, S3OModel, root_for_shared_principal_point
from s3o_warp.motion import losses as L
from s3o_warp.motion.crossings import LimbPair
from s3o_warp.motion.objective import TermContext
from s3o_warp.ops import laplacian_loss, soft_silhouette, symmetry_loss
from s3o_warp.skeleton.edit import fit_bones_to_parts, precision_to_quat_scales

log = logging.getLogger(__name__)

LIFT_DEPTH = 3.0
"""Depth (object-frame units) at which the canonical frame's 2D skeleton is lifted."""
COARSE_SIGMA, COARSE_SIGMA_FINAL = 1.0, 0.1
"""Soft-silhouette blur sigma (square crop pixels) at the start and the end of the coarse fit (geometric decay): a
wide blur inflates thin parts by a pixel or two."""
REFIT_MIN_FACES = 4
"""After the coarse fit, a bone whose part has fewer faces than this stays as the lift made it
(:func:`refit_bones_to_parts`)."""


@dataclass
class CoarseResult:
    init: ModelInit
    canonical: int
    sym_plane: tuple  # (normal (3,), offset)
    parents: np.ndarray  # (B,) kinematic tree of the initial bones (-1 root)
    part_masks: torch.Tensor  # (P,S,S) of the canonical frame
    face_parts: torch.Tensor  # (F,) part index of each face
    joints: tuple = ((), ())  # (bone pairs (J,2), positions (J,3)) in the object frame
    limb_pairs: tuple = ()  # crossings.LimbPair per symmetric limb pair of the lift (one bone each)
    anchors: tuple = ()  # several videos: each video's anchor frame (the canonical frame in its own video)


def coarse_model(data: FitData, cfg: Config) -> CoarseResult:
    """Paper 3.2: canonical frame, 2D skeleton, ellipsoid lift, union mesh and bones (no fitting yet)."""
    masks = data.masks.cpu().numpy() > 0.5
    settings = skeleton2d.CoarseSettings(target_vertices=cfg.coarse.target_vertices)
    if cfg.coarse.canonical_frame is None:
        c, _ratios = skeleton2d.canonical_frame(list(masks), settings, progress=False)
    else:
        c = int(cfg.coarse.canonical_frame)  # within the sequence: prepare_data checked it
        log.info("canonical frame %d (coarse.canonical_frame)", c)
    skel = skeleton2d.skeleton_2d(masks[c], settings)
    S = data.crop_size
    H, W = data.frame_size if data.num_videos == 1 else next(v.frame_size for v in data.videos if v.start <= c < v.stop)
    f_full = 0.5 * W / math.tan(math.radians(cfg.coarse.fov_degrees) / 2)
    f_crop = f_full * float(data.crop_scale[c])
    Kc = np.array([[f_crop, 0, (S - 1) / 2], [0, f_crop, (S - 1) / 2], [0, 0, 1]], dtype=np.float64)
    lifted = lift.lift_to_3d(skel, Kc, LIFT_DEPTH, settings)
    verts, faces = lift.ellipsoid_union_mesh(lifted, settings=settings)
    bones = lift.init_bones(lifted, settings)
    parts = skeleton2d.part_masks(masks[c], skel)
    limb_pairs = _limb_pairs(lifted, bones)
    T = data.num_frames
    root = np.asarray(lifted.root_transform, dtype=np.float64)
    # precision Q = V^T diag(lam) V  ->  orientation V (rows = axes) and log-scales log(lam)
    lam, U = np.linalg.eigh(np.asarray(bones.precisions, dtype=np.float64))
    V = np.transpose(U, (0, 2, 1)).copy()
    V[np.linalg.det(V) < 0, 2] *= -1  # proper rotations
    # face -> part: the part (2D edge) whose bone dominates the face's vertices
    vt = torch.as_tensor(verts, dtype=torch.float32)
    cen = torch.as_tensor(bones.centres, dtype=torch.float32)
    Q = torch.as_tensor(bones.precisions, dtype=torch.float32)
    dv = vt[:, None, :] - cen[None]
    maha = torch.einsum("nbi,bij,nbj->nb", dv, Q, dv)
    edge_of_bone = torch.as_tensor(np.asarray(bones.edge_of_bone), dtype=torch.int64)
    vpart = edge_of_bone[maha.argmin(1)]
    ft = torch.as_tensor(faces, dtype=torch.int64)
    fpart = torch.mode(vpart[ft], dim=1).values
    focal, video_of, motion_of, anchors = float(f_full), None, None, ()
    if data.num_videos > 1:
        focal, video_of, motion_of, anchors = _videos(data, cfg, masks, c, settings)
    root_R = torch.as_tensor(root[:3, :3], dtype=torch.float32).expand(T, 3, 3).clone()
    root_t = torch.as_tensor(root[:3, 3], dtype=torch.float32).expand(T, 3).clone()
    if cfg.motion.principal_point == "shared":  # the object as each crop's centre showed it, one principal point
        root_R, root_t = root_for_shared_principal_point(root_R, root_t, data.crop_to_frame.cpu(), S, f_full,
                                                         ((W - 1) / 2, (H - 1) / 2))
    init = ModelInit(
        verts=vt,
        faces=ft,
        colors=torch.full((len(verts), 3), 0.5),
        centers=cen,
        rotations=torch.as_tensor(V, dtype=torch.float32),
        log_scales=torch.as_tensor(np.log(np.maximum(lam, 1e-8)), dtype=torch.float32),
        root_R=root_R,
        root_t=root_t,
        focal=focal,
        crop_scale=data.crop_scale.cpu(),
        crop_size=S,
        crop_to_frame=data.crop_to_frame.cpu(),
        principal_point=cfg.motion.principal_point,
        frame_size=(H, W),
        video_of=video_of,
        motion_of=motion_of,
    )
    return CoarseResult(
        init=init,
        canonical=int(c),
        sym_plane=(np.asarray(lifted.symmetry_plane[0], dtype=np.float32), float(lifted.symmetry_plane[1])),
        parents=np.asarray(bones.parents),
        joints=(np.asarray(bones.joints), np.asarray(bones.joint_positions)),
        limb_pairs=limb_pairs,
        part_masks=torch.as_tensor(parts, dtype=torch.float32),
        face_parts=fpart,
        anchors=anchors,
    )


def _videos(data: FitData, cfg: Config, masks: np.ndarray, canonical: int, settings):
    """Several videos: each one's focal length (from its own frame width), the video and bone-motion row of every
    frame (synchronized videos share rows frame by frame) and each video's anchor frame (the canonical frame in the
    canonical frame's video, else the frame the canonical rule picks in that video alone)."""
    vids = data.videos
    focal = [0.5 * v.frame_size[1] / math.tan(math.radians(cfg.coarse.fov_degrees) / 2) for v in vids]
    video_of = torch.as_tensor(data.video_of())
    if cfg.motion.synchronized:
        motion_of = torch.cat([torch.arange(v.num_frames) for v in vids])
    else:
        motion_of = torch.arange(data.num_frames)
    anchors = []
    for v in vids:
        if v.start <= canonical < v.stop:
            anchors.append(int(canonical))
        else:
            k, _ = skeleton2d.canonical_frame(list(masks[v.start:v.stop]), settings, progress=False)
            anchors.append(v.start + int(k))
    return focal, video_of, motion_of, tuple(anchors)


def _limb_pairs(lifted, bones) -> tuple:
    """The lift's symmetric limb pairs as ``crossings.LimbPair`` (rest axis from the shared junction)."""
    ends = lift.edge_ends(lifted)
    bone_of_edge = {int(e): b for b, e in enumerate(np.asarray(bones.edge_of_bone))}
    out = []
    for e1, e2 in np.asarray(lifted.sym_pairs).reshape(-1, 2):
        shared = {int(n) for n in lifted.edges[e1]} & {int(n) for n in lifted.edges[e2]}
        if len(shared) != 1 or int(e1) not in bone_of_edge or int(e2) not in bone_of_edge:
            continue
        n = shared.pop()
        axes = []
        for e in (e1, e2):
            i = 0 if int(lifted.edges[e][0]) == n else 1
            axes.append((ends[e, i].copy(), ends[e, 1 - i].copy()))
        out.append(LimbPair(a=bone_of_edge[int(e1)], b=bone_of_edge[int(e2)], top_a=axes[0][0], end_a=axes[0][1],
                            top_b=axes[1][0], end_b=axes[1][1],
                            normal=tuple(float(x) for x in lifted.symmetry_plane[0])))
    return tuple(out)


def coarse_terms(model: S3OModel, data: FitData, coarse: CoarseResult, cc: CoarseConfig, sigma: float,
                 ctx: TermContext) -> tuple[dict, torch.Tensor, torch.Tensor]:
    """The coarse fit's objective on the canonical frame: ``({name: (weight, value)}, soft silhouette (1, S, S),
    mask (1, S, S))``. Terms: silhouette, part silhouettes (each part's faces against its 2D edge's pixels),
    symmetry (eq. 16) and the Laplacian of the change from the lift (eq. 17)."""
    m, device = model, model.verts.device
    fr = torch.tensor([coarse.canonical], device=device)
    verts = m(fr)
    K = m.intrinsics_crop(fr)
    S = data.crop_size
    sil = soft_silhouette(verts, m.faces, K, (S, S), sigma=sigma)
    terms = {"sil": (cc.w_sil, L.silhouette_loss(sil, data.masks[fr]))}
    parts = coarse.part_masks.to(device)
    fp = coarse.face_parts.to(device)
    part_terms = []
    for p in range(parts.shape[0]):
        sel = m.faces[fp == p]
        if len(sel) == 0:
            continue
        ps = soft_silhouette(verts, sel, K, (S, S), sigma=sigma)
        part_terms.append(L.silhouette_loss(ps, parts[p][None]))
    if part_terms:
        terms["part"] = (cc.w_part, torch.stack(part_terms).mean())
    terms["sym"] = (cc.w_sym, symmetry_loss(m.verts, ctx.sym_plane))
    terms["lap"] = (cc.w_lap, laplacian_loss(m.verts - ctx.lap_ref, m.faces))
    return terms, sil, data.masks[fr]


@torch.no_grad()
def refit_bones_to_parts(model: S3OModel, coarse: CoarseResult) -> None:
    """After the coarse fit, each bone onto its coarse part's faces (:func:`s3o_warp.skeleton.edit.fit_bones_to_parts`):
    centre to the part's area centroid, long axis to its principal axis, radii kept. The lift's bone is the
    straight chord of its 2D edge, and a curved part (a tail rising from the rump) leaves it behind, outside the
    Gaussian, so the body's bone takes the part. Only the lift's bones have parts: with other bones (the
    virtual-bones baseline) nothing moves."""
    m = model
    if m.bone_centers.shape[0] != len(coarse.parents):
        return
    C0 = m.bone_centers.detach().cpu().double().numpy()
    C, Q, moved = fit_bones_to_parts(m.verts.detach().cpu(), m.faces.cpu(), coarse.face_parts.cpu(), C0,
                                     m.precisions().detach().cpu(), REFIT_MIN_FACES)
    quats, log_scales = precision_to_quat_scales(Q)
    m.bone_centers.copy_(torch.as_tensor(C).to(m.bone_centers))
    m.bone_quat.copy_(torch.as_tensor(quats).to(m.bone_quat))
    m.bone_log_scales.copy_(torch.as_tensor(log_scales).to(m.bone_log_scales))
    d = np.linalg.norm(C - C0, axis=1)[moved]
    log.info("bones refit to their coarse parts: %d of %d moved, by at most %.3g (mean %.3g)", int(moved.sum()),
             len(C), d.max() if len(d) else 0.0, d.mean() if len(d) else 0.0)
