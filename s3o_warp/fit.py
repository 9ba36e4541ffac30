"""The fit, end to end (paper Algorithm 1): coarse phase, warm-up, shape + motion phase, outputs.

``fit(sequence_dir, out_dir, cfg, device)`` reads the sequence, computes (or loads cached) flow, builds
the coarse model from the canonical frame's 2D skeleton (phase 1), then optimises camera and motion
with the mesh frozen (warm-up) and shape, colour, camera and motion together (phase 2, E-step), and
writes the run directory (DESIGN.md "Run directory"). Checkpoints are written atomically at phase
boundaries and every ``output.checkpoint_every`` steps; ``resume=True`` continues from the last one.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from s3o_warp.motion import losses as L
from s3o_warp.config import Config, check, save_toml, to_dict
from s3o_warp.errors import ConfigError, InputError
from s3o_warp.geometry import project
from s3o_warp.model import ModelInit, S3OModel, root_for_shared_principal_point

log = logging.getLogger(__name__)

CHECKPOINT_VERSION = 3
"""Format of checkpoints and branch checkpoints, bumped when what they hold or the settings they record change; a
checkpoint of another version is refused (its run must be refit)."""
BRANCH_CHECKPOINT = "branch.pt"  # in <run>/checkpoints: the state before the first M-step that reads t_o
BRANCH_LOG = "branch.log.jsonl"
BRANCH_MAY_DIFFER = ("skeleton.t_o", "skeleton.t_u", "skeleton.t_d")
"""The settings a branched fit may change: the refinement reads them only after the branch (and output.*, preset:
no effect on the fit)."""


# ---------------------------------------------------------------------------------------------------
# Data on the device
# ---------------------------------------------------------------------------------------------------


@dataclass
class FitData:
    """Crops of the whole sequence on the fit's device (S = crop side, T frames)."""

    name: str
    frame_names: list
    frame_size: tuple  # (H, W) full frame
    fps: float
    images: "FrameStore"  # (T,S,S,3) float in [0,1], indexed by frame ids
    masks: torch.Tensor  # (T,S,S) float {0,1}
    crop_to_frame: torch.Tensor  # (T,3,3)
    crop_scale: torch.Tensor  # (T,) crop pixels per frame pixel
    flow_fwd: "FrameStore"  # (T-1,S,S,2) crop-t pixels, indexed by pair ids
    conf_fwd: "FrameStore"  # (T-1,S,S) in [0,1]
    sequence_dir: Path
    frame_weight: torch.Tensor | None = None  # (T,) silhouette weight (objects leaving the frame count less)
    open_kwargs: dict | None = None  # how to re-open the sequence (masks=, name=) for pictures
    mask_dir: Path | None = None  # where the sequence's masks are (for scoring)
    keypoints_file: Path | None = None  # keypoints.json beside the sequence, if any (scoring only)
    ground_truth_dir: Path | None = None  # ground_truth/ beside the sequence, if any (scoring only)

    @property
    def num_frames(self) -> int:
        return self.masks.shape[0]

    @property
    def crop_size(self) -> int:
        return self.masks.shape[1]


class FrameStore:
    """Per-frame arrays indexed by a tensor of frame ids, returned as float tensors on the fit's device.

    Resident: one device tensor (fast; short videos). Streamed: numpy arrays or memory maps on disk,
    read per batch, so memory grows with the batch and the resolution, not with the video length.
    """

    def __init__(self, arrays, device: torch.device, scale: float = 1.0, resident: bool = True, stack_axis=None):
        self.device, self.scale, self.resident = device, scale, resident
        self._list = not hasattr(arrays, "shape")  # a sequence of per-frame arrays (e.g. flow pairs)
        if resident:
            a = np.stack([np.asarray(arrays[i]) for i in range(len(arrays))]) if self._list else np.asarray(arrays)
            self._data = torch.from_numpy(a.astype(np.float32) * scale if scale != 1.0 else a.astype(np.float32)).to(device)
        else:
            self._data = arrays

    def __len__(self) -> int:
        return len(self._data)

    def __getitem__(self, frames) -> torch.Tensor:
        if self.resident:
            return self._data[frames]
        idx = frames.detach().cpu().numpy() if isinstance(frames, torch.Tensor) else np.asarray(frames)
        if self._list:
            a = np.stack([np.asarray(self._data[int(i)]) for i in np.atleast_1d(idx)])
            if np.ndim(idx) == 0:
                a = a[0]
        else:
            a = np.asarray(self._data[idx])
        t = torch.from_numpy(np.ascontiguousarray(a)).to(self.device).float()
        return t * self.scale if self.scale != 1.0 else t


class _PairField:
    """Lazy list over a FlowCache: element t is one field of pair t (a memory-mapped array)."""

    def __init__(self, flow, field: str):
        self.flow, self.field = flow, field

    def __len__(self) -> int:
        return len(self.flow)

    def __getitem__(self, t: int):
        return getattr(self.flow.pair(int(t)), self.field)


def prepare_data(sequence_dir: Path, cfg: Config, run_dir: Path, device: torch.device, masks=None, name=None) -> FitData:
    """Open the sequence, crop every frame and compute (or load) the forward flow and its confidence.

    Sequences of up to ``data.resident_max_frames`` frames live in (device) memory; longer ones are
    streamed: crops go to a memory-mapped file in ``<run>/cache`` and flow stays in its per-pair cache.
    """
    from s3o_warp.data import sequence as video

    open_kwargs = {"masks": masks, "name": name}
    seq = video.open_sequence(sequence_dir, cfg=cfg.data, **open_kwargs)
    T = seq.num_frames
    if T < 2:
        raise InputError(f"sequence {sequence_dir} has {T} frame(s); the fit needs at least 2")
    if cfg.coarse.canonical_frame is not None and cfg.coarse.canonical_frame >= T:
        raise ConfigError(f"coarse.canonical_frame={cfg.coarse.canonical_frame}: the sequence has frames 0-{T - 1}; "
                          "pick one of them or leave it unset for the automatic choice")
    S = cfg.data.crop_size
    resident = T <= cfg.data.resident_max_frames
    mask_crops = np.zeros((T, S, S), np.bool_)
    c2f = np.zeros((T, 3, 3), np.float32)
    if resident:
        imgs = np.zeros((T, S, S, 3), np.uint8)
    else:
        (run_dir / "cache").mkdir(parents=True, exist_ok=True)
        key = "-".join(seq.mask_digests[:1] + seq.mask_digests[-1:])[:24]
        path = run_dir / "cache" / f"crops_{T}_{S}_{key}.npy"
        imgs = np.lib.format.open_memmap(path, mode="w+", dtype=np.uint8, shape=(T, S, S, 3))
    for k, crop in enumerate(seq.crops()):
        imgs[k] = crop.image
        mask_crops[k] = crop.mask
        c2f[k] = crop.crop_to_frame
    flow = video.compute_flow(seq, run_dir / "cache", cfg.data)
    dev = dict(device=device)
    return FitData(
        name=seq.name,
        frame_names=list(seq.frame_names),
        frame_size=tuple(int(x) for x in seq.size),
        fps=float(seq.fps),
        images=FrameStore(imgs, device, scale=1.0 / 255.0, resident=resident),
        masks=torch.from_numpy(mask_crops.astype(np.float32)).to(**dev),
        crop_to_frame=torch.from_numpy(c2f).to(**dev),
        crop_scale=torch.from_numpy(1.0 / c2f[:, 0, 0]).to(**dev),
        flow_fwd=FrameStore(_PairField(flow, "flow_fwd"), device, resident=resident),
        conf_fwd=FrameStore(_PairField(flow, "conf_fwd"), device, resident=resident),
        sequence_dir=Path(sequence_dir),
        frame_weight=torch.as_tensor(
            np.where(np.asarray(seq.touches_border), video.BORDER_WEIGHT, 1.0), dtype=torch.float32, device=device
        ),
        open_kwargs=open_kwargs,
        mask_dir=Path(seq.mask_files[0]).parent,
        keypoints_file=seq.keypoints_file,
        ground_truth_dir=seq.ground_truth_dir,
    )


# ---------------------------------------------------------------------------------------------------
# Phase 1: coarse model
# ---------------------------------------------------------------------------------------------------


LIFT_DEPTH = 3.0
"""Depth (object-frame units) at which the canonical frame's 2D skeleton is lifted."""
COARSE_SIGMA, COARSE_SIGMA_FINAL = 1.0, 0.1
"""Soft-silhouette blur sigma (square crop pixels) at the start and the end of the coarse fit (geometric decay): a
wide blur inflates thin parts by a pixel or two."""
REFIT_MIN_FACES = 4
"""After the coarse fit, a bone whose part has fewer faces than this stays as the lift made it
(:meth:`Fitter.refit_bones_to_parts`)."""


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


def coarse_model(data: FitData, cfg: Config) -> CoarseResult:
    """Paper 3.2: canonical frame, 2D skeleton, ellipsoid lift, union mesh and bones (no fitting yet)."""
    from s3o_warp import coarse

    masks = data.masks.cpu().numpy() > 0.5
    settings = coarse.CoarseSettings(target_vertices=cfg.coarse.target_vertices)
    if cfg.coarse.canonical_frame is None:
        c, _ratios = coarse.canonical_frame(list(masks), settings, progress=False)
    else:
        c = int(cfg.coarse.canonical_frame)  # within the sequence: prepare_data checked it
        log.info("canonical frame %d (coarse.canonical_frame)", c)
    skel = coarse.skeleton_2d(masks[c], settings)
    S = data.crop_size
    H, W = data.frame_size
    f_full = 0.5 * W / math.tan(math.radians(cfg.coarse.fov_degrees) / 2)
    f_crop = f_full * float(data.crop_scale[c])
    Kc = np.array([[f_crop, 0, (S - 1) / 2], [0, f_crop, (S - 1) / 2], [0, 0, 1]], dtype=np.float64)
    lifted = coarse.lift_to_3d(skel, Kc, LIFT_DEPTH, settings)
    verts, faces = coarse.ellipsoid_union_mesh(lifted, settings=settings)
    bones = coarse.init_bones(lifted, settings)
    parts = coarse.part_masks(masks[c], skel)
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
        focal=float(f_full),
        crop_scale=data.crop_scale.cpu(),
        crop_size=S,
        crop_to_frame=data.crop_to_frame.cpu(),
        principal_point=cfg.motion.principal_point,
        frame_size=(H, W),
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
    )


def _limb_pairs(lifted, bones) -> tuple:
    """The lift's symmetric limb pairs as ``crossings.LimbPair`` (rest axis from the shared junction)."""
    from s3o_warp.coarse.lift import edge_ends
    from s3o_warp.motion.crossings import LimbPair

    ends = edge_ends(lifted)
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
                            top_b=axes[1][0], end_b=axes[1][1]))
    return tuple(out)


# ---------------------------------------------------------------------------------------------------
# Optimisation
# ---------------------------------------------------------------------------------------------------

PHASES = ("coarse", "warmup", "joint")

HYPOTHESIS_REFINE = 3
"""Camera hypotheses: the best this many go on for HYPOTHESIS_REFINE_STEPS more steps and are ranked again (0 or 1 =
no second round): after ``motion.hypothesis_steps`` the scores of neighbouring turn rates are often within a few
per cent (DAVIS dog: within 1.5 %; after the second round the rate the other seeds pick leads by 5-10 %)."""
HYPOTHESIS_REFINE_STEPS = 60
"""Further steps of each refined hypothesis."""
WARMUP_SWEEP = 0.5
"""Fraction of the warm-up that sweeps windows outward from the canonical frame, each new frame starting from its
nearest already-fitted neighbour's pose (the rest of the warm-up: random windows)."""
COVER_PIXELS = 256
"""Uncovered mask pixels sampled per frame for the coverage loss (0 = all)."""


NAN_LR_FACTOR = 0.5
"""On a NaN/Inf loss or gradient: skip the step, roll back to the last good state, scale learning rates by this."""
NAN_MAX_CONSECUTIVE = 5
"""Stop the fit (naming the loss term) after this many NaN/Inf steps in a row."""
SNAPSHOT_EVERY = 10
"""Keep an in-memory copy of the last good state every this many steps (the NaN roll-back target)."""


class FitDiverged(InputError):
    """The loss or its gradient stayed NaN/Inf for several steps in a row; the message names the term."""


class FitInterrupted(Exception):
    """Raised after a stop request (Ctrl-C, SIGTERM) once the checkpoint of the current step is written."""


def _atomic_save(obj, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def _atomic_copy(src: Path, dst: Path) -> None:
    """``dst`` becomes a copy of ``src`` (empty when ``src`` is missing), written to a temporary name, then renamed."""
    tmp = dst.with_name(dst.name + ".tmp")
    tmp.write_bytes(src.read_bytes() if src.is_file() else b"")
    os.replace(tmp, dst)


class Fitter:
    """Runs the phases with one Adam optimiser per phase, logging and atomic checkpoints."""

    def __init__(self, data: FitData, coarse_res: CoarseResult, cfg: Config, run_dir: Path, device):
        from s3o_warp.kernels.regularisers import mesh_edges

        self.data, self.cfg, self.run_dir, self.device = data, cfg, Path(run_dir), device
        check(cfg)  # a Config built in code, not by make_config: refused before any work
        self.coarse = coarse_res
        self.model = S3OModel(coarse_res.init).to(device)
        self.edges = mesh_edges(self.model.faces).to(device)
        self.lap_ref = self.model.verts.detach().clone()  # reference shape of the relative Laplacian term
        self.sym_plane = (torch.as_tensor(coarse_res.sym_plane[0], device=device), coarse_res.sym_plane[1])
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.phase = PHASES[0]
        self.step = 0  # step within the phase
        self.log_file = self.run_dir / "log.jsonl"
        self.t0 = time.perf_counter()
        self.history: list[dict] = []
        self.opt = self._make_optimizer()
        self._stop = False
        self._bad = 0
        self._pending_m_step = False  # a branch checkpoint was loaded: its M-step runs before the next step
        self._good = None
        from s3o_warp.skeleton.mstep import SkeletonState, refresh_joints, virtual_bones_init

        parents = np.asarray(coarse_res.parents, np.int64)
        if cfg.skeleton.method == "virtual":
            parents = virtual_bones_init(self.model, cfg)
            self.opt = self._make_optimizer()
        self.skel = SkeletonState(parents=parents)
        v0 = self.model.verts.detach()
        self.size = float((v0.max(0).values - v0.min(0).values).norm())  # the object's size (bbox diagonal)
        refresh_joints(self.model, self.skel, cfg.skeleton)

    # -- NaN/Inf guard ------------------------------------------------------------------------------
    @staticmethod
    def _non_finite(terms: dict, total: torch.Tensor) -> str | None:
        for k, (w, v) in terms.items():
            if not torch.isfinite(v.detach()).all():
                return f"loss term '{k}'"
        return None if torch.isfinite(total.detach()) else "total loss"

    def _non_finite_grad(self) -> str | None:
        names = {id(p): n for n, p in self.model.named_parameters()}
        for g in self.opt.param_groups:
            for p in g["params"]:
                if p.grad is not None and not torch.isfinite(p.grad).all():
                    return f"gradient of '{names.get(id(p), '?')}'"
        return None

    def _snapshot(self) -> None:
        import copy

        self._good = (copy.deepcopy(self.model.state_dict()), copy.deepcopy(self.opt.state_dict()))

    def _recover(self, what: str) -> None:
        """Skip the step, roll back to the last good state and lower the learning rates."""
        self._bad += 1
        if self._bad >= NAN_MAX_CONSECUTIVE:
            path = self.save_checkpoint() if self._good is not None else None
            raise FitDiverged(
                f"the fit diverged: {what} was NaN/Inf for {self._bad} steps in a row in phase '{self.phase}' "
                f"at step {self.step}; lower the learning rates or that term's weight (last good checkpoint: {path})"
            )
        if self._good is not None:
            self.model.load_state_dict(self._good[0])
            lrs = [g["lr"] for g in self.opt.param_groups]
            self.opt.load_state_dict(self._good[1])
            for g, lr in zip(self.opt.param_groups, lrs):
                g["lr"] = lr
        for g in self.opt.param_groups:
            g["lr"] *= NAN_LR_FACTOR
        self.opt.zero_grad(set_to_none=True)
        log.warning("%s is NaN/Inf at %s step %d: step skipped, rolled back, learning rates x%g",
                    what, self.phase, self.step, NAN_LR_FACTOR)

    @torch.no_grad()
    def refit_bones_to_parts(self) -> None:
        """After the coarse fit, each bone onto its coarse part's faces (``skeleton_edit.fit_bones_to_parts``): centre
        to the part's area centroid, long axis to its principal axis, radii kept. The lift's bone is the straight
        chord of its 2D edge, and a curved part (a tail rising from the rump) leaves it behind, outside the
        Gaussian, so the body's bone takes the part.

        Only the lift's bones have parts: with ``skeleton.method=virtual`` (k-means bones) nothing moves.
        """
        from s3o_warp.skeleton.edit import fit_bones_to_parts, precision_to_quat_scales

        m = self.model
        if self.cfg.skeleton.method != "s3o" or m.bone_centers.shape[0] != len(self.coarse.parents):
            return
        C0 = m.bone_centers.detach().cpu().double().numpy()
        C, Q, moved = fit_bones_to_parts(m.verts.detach().cpu(), m.faces.cpu(), self.coarse.face_parts.cpu(), C0,
                                         m.precisions().detach().cpu(), REFIT_MIN_FACES)
        quats, log_scales = precision_to_quat_scales(Q)
        m.bone_centers.copy_(torch.as_tensor(C).to(m.bone_centers))
        m.bone_quat.copy_(torch.as_tensor(quats).to(m.bone_quat))
        m.bone_log_scales.copy_(torch.as_tensor(log_scales).to(m.bone_log_scales))
        d = np.linalg.norm(C - C0, axis=1)[moved]
        log.info("bones refit to their coarse parts: %d of %d moved, by at most %.3g (mean %.3g)", int(moved.sum()),
                 len(C), d.max() if len(d) else 0.0, d.mean() if len(d) else 0.0)

    def request_stop(self) -> None:
        """Ask the loop to checkpoint and stop at the next step boundary (safe from a signal handler)."""
        self._stop = True

    # -- optimiser per phase ------------------------------------------------------------------------
    def _make_optimizer(self) -> torch.optim.Optimizer:
        m, mc, cc = self.model, self.cfg.motion, self.cfg.coarse
        if self.phase == "coarse":
            groups = [{"params": [m.verts], "lr": cc.lr, "name": "shape"}]
        elif self.phase == "warmup":
            groups = [
                {"params": [m.root_aa, m.root_t, m.bone_aa, m.bone_t], "lr": mc.lr_motion, "name": "motion"},
                {"params": [m.log_focal, m.pp], "lr": mc.lr_camera, "name": "camera"},
            ]
        else:
            groups = [
                {"params": [m.root_aa, m.root_t, m.bone_aa, m.bone_t], "lr": mc.lr_motion, "name": "motion"},
                {"params": [m.log_focal, m.pp], "lr": mc.lr_camera, "name": "camera"},
                {"params": [m.verts], "lr": mc.lr_shape, "name": "shape"},
                {"params": [m.color_logits], "lr": mc.lr_color, "name": "color"},
                {"params": [m.bone_centers, m.bone_quat, m.bone_log_scales], "lr": mc.lr_bones, "name": "bones"},
            ]
        return torch.optim.Adam(groups)

    def phase_steps(self, phase: str) -> int:
        mc = self.cfg.motion
        return {"coarse": self.cfg.coarse.steps, "warmup": mc.warmup_steps, "joint": mc.steps}[phase]

    # -- losses -------------------------------------------------------------------------------------
    def coarse_losses(self) -> dict:
        from s3o_warp.kernels.raster import soft_silhouette
        from s3o_warp.kernels.regularisers import laplacian_loss, symmetry_loss

        m, cc, d = self.model, self.cfg.coarse, self.data
        c = self.coarse.canonical
        fr = torch.tensor([c], device=self.device)
        verts = m(fr)
        K = m.intrinsics_crop(fr)
        S = d.crop_size
        sigma = self.sigma(COARSE_SIGMA, COARSE_SIGMA_FINAL)
        sil = soft_silhouette(verts, m.faces, K, (S, S), sigma=sigma)
        terms = {"sil": (cc.w_sil, L.silhouette_loss(sil, d.masks[fr]))}
        parts = self.coarse.part_masks.to(self.device)
        fp = self.coarse.face_parts.to(self.device)
        part_terms = []
        for p in range(parts.shape[0]):
            sel = m.faces[fp == p]
            if len(sel) == 0:
                continue
            ps = soft_silhouette(verts, sel, K, (S, S), sigma=sigma)
            part_terms.append(L.silhouette_loss(ps, parts[p][None]))
        if part_terms:
            terms["part"] = (cc.w_part, torch.stack(part_terms).mean())
        terms["sym"] = (cc.w_sym, symmetry_loss(m.verts, self.sym_plane))
        terms["lap"] = (cc.w_lap, laplacian_loss(m.verts - self.lap_ref, m.faces))
        return terms, sil, d.masks[fr]

    def sweep_starts(self, stride: int | None = None) -> list[int]:
        """Window starts of the warm-up sweep: the canonical frame's window, then outward both ways, ``stride``
        frames per stage (None: half the window, the fit's)."""
        T = self.data.num_frames
        n = min(self.cfg.motion.batch_frames, T)
        stride = max(1, stride or n // 2)
        s0 = min(max(self.coarse.canonical - n // 2, 0), T - n)
        right = list(range(s0 + stride, T - n + 1, stride))
        if right and right[-1] != T - n:
            right.append(T - n)
        left = list(range(s0 - stride, -1, -stride))
        if left and left[-1] != 0:
            left.append(0)
        order = [s0]
        for k in range(max(len(left), len(right))):
            order += ([right[k]] if k < len(right) else []) + ([left[k]] if k < len(left) else [])
        return order

    def sigma(self, start: float, final: float) -> float:
        """Soft-silhouette sigma of the current step: geometric decay from start to final over the phase."""
        n = max(1, self.phase_steps(self.phase) - 1)
        return float(start * (final / start) ** min(1.0, self.step / n))

    def window(self) -> torch.Tensor:
        T = self.data.num_frames
        n = min(self.cfg.motion.batch_frames, T)
        mc = self.cfg.motion
        sweep_steps = int(WARMUP_SWEEP * mc.warmup_steps) if self.phase == "warmup" else 0
        if self.step < sweep_steps:
            starts = self.sweep_starts()
            per = max(1, sweep_steps // len(starts))
            start = starts[min(self.step // per, len(starts) - 1)]
            frames = torch.arange(start, start + n, device=self.device)
            self._seed_unvisited(frames)
            return frames
        return self._random_window()

    def _random_window(self) -> torch.Tensor:
        """A window of consecutive frames around a uniformly drawn frame (clamped, so ends are covered too)."""
        T = self.data.num_frames
        n = min(self.cfg.motion.batch_frames, T)
        centre = int(torch.randint(0, T, (1,), generator=self.gen))
        start = min(max(centre - n // 2, 0), T - n)
        return torch.arange(start, start + n, device=self.device)

    @torch.no_grad()
    def _seed_unvisited(self, frames: torch.Tensor) -> None:
        """Frames entering the sweep for the first time start from the nearest visited frame's pose."""
        m = self.model
        visited = m.visited
        if not bool(visited.any()):
            visited[self.coarse.canonical] = True
        idx = torch.nonzero(visited).flatten()
        for f in frames.tolist():
            if visited[f]:
                continue
            src = int(idx[(idx - f).abs().argmin()])
            for p in (m.root_aa, m.root_t, m.bone_aa, m.bone_t):
                p.data[f] = p.data[src]
        visited[frames] = True

    def motion_losses(self, frames: torch.Tensor) -> dict:
        from s3o_warp.kernels.raster import interpolate, rasterize, soft_silhouette
        from s3o_warp.kernels.regularisers import arap_loss, dynamic_rigidity_loss, laplacian_loss, symmetry_loss

        m, mc, d = self.model, self.cfg.motion, self.data
        S = d.crop_size
        W = m.skinning()
        verts = m(frames, weights=W)
        K = m.intrinsics_crop(frames)
        sil = soft_silhouette(verts, m.faces, K, (S, S), sigma=self.sigma(mc.sigma, mc.sigma_final))
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
            fi = face_index[:-1]
            rflow = interpolate(vflow, m.faces, fi, bary[:-1])
            pairs = frames[:-1]
            valid = fg[:-1] * mask[:-1]
            terms["flow"] = (mc.w_flow, L.flow_loss(rflow, d.flow_fwd[pairs], d.conf_fwd[pairs], valid))
        if len(frames) > 1 and mc.rigidity != "none" and mc.w_rigid > 0:
            if mc.rigidity == "dynamic":
                terms["rigid"] = (mc.w_rigid, dynamic_rigidity_loss(verts, self.edges, W.detach()))
            else:
                terms["rigid"] = (mc.w_rigid, arap_loss(verts, self.edges))
        if mc.w_joint > 0 and len(self.skel.joints):
            J, P = self._joint_tensors()
            terms["joint"] = (mc.w_joint, L.joint_attachment_loss(m.bone_rt(frames), J, P, self.size))
        if self.phase == "joint":
            terms["lap"] = (mc.w_lap, laplacian_loss(m.verts - self.lap_ref, m.faces))
            terms["sym"] = (mc.w_sym, symmetry_loss(m.verts, self.sym_plane))
        smooth = (
            L.temporal_smoothness(m.root_aa)
            + L.temporal_smoothness(m.root_t)
            + L.temporal_smoothness(m.bone_aa)
            + L.temporal_smoothness(m.bone_t)
        )
        terms["smooth"] = (mc.w_smooth, smooth)
        terms["bone_reg"] = (mc.w_bone_reg, (m.bone_t[frames] ** 2).mean())
        return terms, sil, mask

    def _joint_tensors(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The skeleton's joints (bone pairs, rest positions) on the device, copied again only after an
        M-step has replaced them (``refresh_joints`` assigns new arrays), not every step."""
        src = (self.skel.joints, self.skel.joint_positions)
        old = getattr(self, "_joints_src", None)  # held, so the arrays compared by identity stay alive
        if old is None or old[0] is not src[0] or old[1] is not src[1]:
            self._joints_dev = (torch.as_tensor(src[0], dtype=torch.long, device=self.device),
                                torch.as_tensor(src[1], dtype=torch.float32, device=self.device))
            self._joints_src = src
        return self._joints_dev

    @torch.no_grad()
    def hard_iou(self) -> float:
        """Mean over all frames of the hard-render IoU with the crop masks (what the metrics measure)."""
        from s3o_warp.kernels.raster import rasterize

        m, d, S = self.model, self.data, self.data.crop_size
        W = m.skinning()
        ious = []
        for s in range(0, d.num_frames, self.cfg.motion.batch_frames):
            fr = torch.arange(s, min(s + self.cfg.motion.batch_frames, d.num_frames), device=self.device)
            fi, _, _ = rasterize(m(fr, weights=W), m.faces, m.intrinsics_crop(fr), (S, S))
            ious.append(L.soft_iou((fi >= 0).float(), d.masks[fr]))
        return float(torch.cat(ious).mean())

    def _log(self, rec: dict) -> None:
        if rec.get("phase") == "eval":
            import resource

            rec["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
        self.history.append(rec)
        with open(self.log_file, "a") as fh:
            fh.write(json.dumps(rec) + "\n")

    # -- loop ---------------------------------------------------------------------------------------
    def run(self) -> None:
        if self.phase == PHASES[0] and self.step == 0:
            self._log({"phase": "eval", "step": 0, "seconds": round(time.perf_counter() - self.t0, 3),
                       "what": "initial", "iou_all_frames": self.hard_iou()})
        for phase in PHASES[PHASES.index(self.phase):]:
            if phase != self.phase:
                if self.phase == "coarse":
                    self.refit_bones_to_parts()
                if phase == "joint" and self.cfg.motion.resolve_crossings:
                    self.resolve_crossings()
                self.phase, self.step = phase, 0
                self.opt = self._make_optimizer()
                self.lap_ref = self.model.verts.detach().clone()
                self._good = None
                self.save_checkpoint()
            n = self.phase_steps(phase)
            if phase == "warmup" and self.step == 0 and (self.cfg.motion.hypotheses > 1
                                                         or self.cfg.motion.turn_rate is not None):
                self.select_hypothesis()
            bar = tqdm(total=n, initial=self.step, desc=f"{phase:>6}", dynamic_ncols=True, leave=True)
            if self._pending_m_step:  # branched from another run's branch checkpoint: its M-step, with this t_o
                self._pending_m_step = False
                self._m_step(n)
            while self.step < n:
                self.opt.zero_grad(set_to_none=True)
                frames = None
                if phase == "coarse":
                    terms, sil, mask = self.coarse_losses()
                else:
                    frames = self.window()
                    terms, sil, mask = self.motion_losses(frames)
                total = sum(w * v for w, v in terms.values())
                bad = self._non_finite(terms, total)
                if bad is None:
                    total.backward()
                    if phase == "coarse" and self.model.verts.grad is not None:  # one view says nothing about depth:
                        self.model.verts.grad[:, 2] = 0  # object z = the canonical camera's depth axis
                    bad = self._non_finite_grad()
                if bad is not None:
                    self._recover(bad)
                    continue
                self._step_window(frames)
                self.step += 1
                self._bad = 0
                if self.step % SNAPSHOT_EVERY == 0 or self._good is None:
                    self._snapshot()
                bar.update(1)
                if self.step % self.cfg.motion.log_every == 0 or self.step == n:
                    iou = float(L.soft_iou(sil.detach(), mask).mean())
                    total = total.detach()
                    rec = {
                        "phase": phase,
                        "step": self.step,
                        "seconds": round(time.perf_counter() - self.t0, 3),
                        "loss": float(total),
                        "iou": iou,
                        "lr": {g["name"]: g["lr"] for g in self.opt.param_groups},
                        "terms": {k: float(v.detach()) for k, (w, v) in terms.items()},
                        "weighted": {k: float(w * v.detach()) for k, (w, v) in terms.items()},
                    }
                    self._log(rec)
                    bar.set_postfix(loss=f"{float(total):.4f}", iou=f"{iou:.3f}")
                if phase == "joint" and self._epoch_end(n):
                    if self.cfg.motion.resolve_crossings and self.step == self.steps_per_epoch(n):
                        # once more when the legs fit better than after the warm-up, with the lift's bones (before
                        # any M-step)
                        self.resolve_crossings()
                    if self.cfg.output.branch_checkpoint and self.is_branch_point(n):
                        self.save_branch_checkpoint()
                    self._m_step(n)
                if self._stop:
                    bar.close()
                    path = self.save_checkpoint()
                    raise FitInterrupted(f"stopped at {phase} step {self.step}; checkpoint {path}")
                if self.step % self.cfg.output.checkpoint_every == 0 and self.step < n:
                    self.save_checkpoint()
            bar.close()
        self._log({"phase": "eval", "step": 0, "seconds": round(time.perf_counter() - self.t0, 3),
                   "what": "final", "iou_all_frames": self.hard_iou()})
        if self.phase != "done":
            self.final_skeleton()
        self.phase, self.step = "done", 0
        self.save_checkpoint()

    def final_skeleton(self) -> None:
        """The shape moved since the last M-step: bones left owning no vertex go (not in the paper), and the joints
        are placed on the final mesh."""
        from s3o_warp.skeleton.mstep import prune_empty_bones, refresh_joints

        sc = self.cfg.skeleton
        if not (sc.method == "s3o" and prune_empty_bones(self.model, self.opt, self.skel, sc)):
            refresh_joints(self.model, self.skel, sc)

    def resolve_crossings(self) -> list[int]:
        """Paired limbs swing through their crossings instead of bouncing (``s3o_warp.motion.crossings``); logs
        and returns the number of exchanged frames per pair."""
        from s3o_warp.motion.crossings import resolve_crossings

        m = self.model
        virtual = self.cfg.skeleton.method == "virtual"  # k-means bones: the lift's pairs do not apply
        pairs = [] if virtual else [p for p in self.coarse.limb_pairs if max(p.a, p.b) < m.num_bones]
        before = (m.bone_aa.detach().clone(), m.bone_t.detach().clone())
        with torch.no_grad():
            fr = torch.arange(m.num_frames, device=self.device)
            Rt = m.root_rt(fr).double().cpu()
            Kf = m.intrinsics_frame(fr).double().cpu()

        def image(P: np.ndarray) -> np.ndarray:
            """Object-frame points (T, 3), one per frame -> full-frame pixels (T, 2)."""
            cam = (Rt[:, :, :3] @ torch.as_tensor(P, dtype=torch.float64)[..., None])[..., 0] + Rt[:, :, 3]
            return project(cam[:, None], Kf)[:, 0].numpy()
        counts = resolve_crossings(m.bone_aa, m.bone_t, m.bone_centers, pairs, self.coarse.canonical,
                                   project=image) if pairs else []
        for p, old in zip((m.bone_aa, m.bone_t), before):  # Adam's moments of a rewritten frame are the
            st = self.opt.state.get(p)                     # partner's: start them afresh
            changed = (p.detach() != old).any(-1)
            if st and changed.any():
                for key in ("exp_avg", "exp_avg_sq"):
                    if key in st:
                        st[key][changed] = 0
        self._log({"phase": "eval", "step": self.step, "seconds": round(time.perf_counter() - self.t0, 3),
                   "what": "crossings", "pairs": [[p.a, p.b] for p in pairs], "exchanged_frames": counts})
        log.info("crossings: %d limb pairs, exchanged frames %s", len(pairs), counts)
        return counts

    def select_hypothesis(self) -> float:
        """Score root-rotation hypotheses (constant turn rates about the object's vertical axis) by a short
        warm-up each and keep the best (LASR/S3O's camera hypotheses); returns the chosen rate (deg/frame)."""
        import copy

        from s3o_warp.geometry import axis_angle_to_matrix

        mc, m = self.cfg.motion, self.model
        base = copy.deepcopy(m.state_dict())
        T, c = m.num_frames, self.coarse.canonical
        rates = np.linspace(-mc.hypothesis_max_rate, mc.hypothesis_max_rate, mc.hypotheses)
        if 0.0 not in rates:
            rates = np.append(rates, 0.0)
        gen_state = self.gen.get_state()

        def apply(rate: float) -> None:
            m.load_state_dict(base)
            ang = torch.deg2rad(torch.tensor(rate * (np.arange(T) - c), dtype=torch.float32, device=self.device))
            aa = torch.zeros(T, 3, device=self.device)
            aa[:, 1] = ang
            with torch.no_grad():
                m.root_R0.copy_(base["root_R0"] @ axis_angle_to_matrix(aa))

        def optimiser() -> torch.optim.Optimizer:
            """Only the root and the camera are free: with the bones free too, they absorb a wrong turn."""
            return torch.optim.Adam([
                {"params": [m.root_aa, m.root_t], "lr": mc.lr_motion, "name": "motion"},
                {"params": [m.log_focal, m.pp], "lr": mc.lr_camera, "name": "camera"}])

        def train(steps: int) -> float:
            """``steps`` warm-up steps on random windows from the current state, then this hypothesis' score: its
            optical-flow term over every frame (texture motion tells a turn from a deformation), or the whole loss
            when the sequence has no flow term."""
            for _ in range(steps):
                frames = self._random_window()
                self.opt.zero_grad(set_to_none=True)
                terms, _, _ = self.motion_losses(frames)
                total = sum(w * v for w, v in terms.values())
                if not torch.isfinite(total):
                    self.step = 0
                    return float("inf")
                total.backward()
                self._step_window(frames)
                self.step += 1
            self.step = 0
            terms = self.mean_terms()
            return terms["flow"] if "flow" in terms else sum(terms.values())

        refined: dict[float, float] = {}
        if mc.turn_rate is not None:
            rates, scores = np.array([float(mc.turn_rate)]), [float("nan")]
        else:
            scores, snaps = [], []
            keep = HYPOTHESIS_REFINE > 1 and HYPOTHESIS_REFINE_STEPS > 0
            for rate in rates:
                apply(float(rate))
                self.gen.set_state(gen_state)
                self.opt = optimiser()
                scores.append(train(mc.hypothesis_steps))
                snaps.append((copy.deepcopy(m.state_dict()), copy.deepcopy(self.opt.state_dict()),
                              self.gen.get_state()) if keep else None)
            if keep:  # the best few go on from where they stopped and are ranked again
                top = [int(i) for i in np.argsort(scores)[:HYPOTHESIS_REFINE] if np.isfinite(scores[i])]
                for i in top:
                    m.load_state_dict(snaps[i][0])
                    self.opt = optimiser()
                    self.opt.load_state_dict(snaps[i][1])
                    self.gen.set_state(snaps[0][2])  # the same windows for every finalist
                    refined[float(rates[i])] = train(HYPOTHESIS_REFINE_STEPS)
                del snaps
        if refined:
            best = min(refined, key=refined.get)
        else:
            best = float(rates[int(np.argmin(scores))] if mc.turn_rate is None else rates[0])
        apply(best)
        m.visited.zero_()
        self.gen.set_state(gen_state)
        self.opt = self._make_optimizer()
        self._log({"phase": "eval", "step": 0, "seconds": round(time.perf_counter() - self.t0, 3), "what": "hypotheses",
                   "rates_deg_per_frame": [float(r) for r in rates], "scores": scores,
                   "refined": {f"{r:g}": v for r, v in refined.items()}, "chosen": best})
        log.info("camera hypotheses: turn rate %.2f deg/frame chosen (scores %s%s)", best,
                 ", ".join(f"{x:.4f}" for x in scores),
                 "; refined " + ", ".join(f"{r:g}: {v:.4f}" for r, v in refined.items()) if refined else "")
        return best

    @torch.no_grad()
    def mean_terms(self) -> dict[str, float]:
        """Every weighted motion loss term averaged over windows that cover every frame (no step taken)."""
        T = self.data.num_frames
        n = min(self.cfg.motion.batch_frames, T)
        starts = list(range(0, T - n + 1, max(n - 1, 1)))  # consecutive windows share a frame: every pair
        if starts[-1] != T - n:
            starts.append(T - n)
        acc: dict[str, list[float]] = {}
        for s in starts:
            terms, _, _ = self.motion_losses(torch.arange(s, s + n, device=self.device))
            for k, (w, v) in terms.items():
                acc.setdefault(k, []).append(float(w * v))
        return {k: float(np.mean(v)) for k, v in acc.items()}

    def _step_window(self, frames: torch.Tensor | None) -> None:
        """Optimiser step that moves per-frame parameters only for the frames of this batch.

        Adam keeps momentum per entry, so frames outside the window would otherwise keep drifting on
        stale momentum between their visits (visible as jitter and a growing flow error).
        """
        if frames is None:
            self.opt.step()
            return
        m = self.model
        keep = torch.ones(m.num_frames, dtype=torch.bool, device=frames.device)
        keep[frames] = False
        per_frame = (m.root_aa, m.root_t, m.bone_aa, m.bone_t) + (() if m.pp_shared else (m.pp,))
        saved = [p.data[keep].clone() for p in per_frame]
        self.opt.step()
        for p, v in zip(per_frame, saved):
            p.data[keep] = v

    # -- skeleton learning ---------------------------------------------------------------------------
    def steps_per_epoch(self, n: int) -> int:
        return max(1, math.ceil(n / max(1, self.cfg.skeleton.epochs)))

    def _epoch_end(self, n: int) -> bool:
        spe = self.steps_per_epoch(n)
        return self.step % spe == 0 and self.step < n

    def is_branch_point(self, n: int) -> bool:
        """At a joint-phase epoch end: is the M-step about to run the first that reads ``skeleton.t_o`` (the first
        merge, after epoch e1 + 1)? Everything before it is the same for every t_o."""
        sc = self.cfg.skeleton
        return sc.method == "s3o" and self.step // self.steps_per_epoch(n) - 1 == sc.e1 + 1

    def _m_step(self, n: int) -> None:
        from s3o_warp.skeleton.mstep import m_step

        epoch = self.step // self.steps_per_epoch(n) - 1
        if m_step(self.model, self.opt, self.data, self.cfg, self.skel, epoch):
            self._good = None  # shapes changed: the NaN roll-back target is taken anew
        every = self.cfg.motion.resample_epochs
        if every > 0 and (epoch + 1) % every == 0:
            self.resample_mesh()

    @torch.no_grad()
    def resample_mesh(self) -> None:
        """Even resampling (paper B): same surface, uniform vertices; colours carried, skinning follows the bones."""
        from s3o_warp.resample import METHODS, ResampleSettings, even_resample

        m = self.model
        target = self.cfg.motion.resample_vertices or len(self.coarse.init.verts)
        n0 = m.verts.shape[0]
        for method in METHODS:
            if method != METHODS[0]:
                log.info("even resampling: trying %s on the same mesh", method)
            rs = ResampleSettings(method=method, target_vertices=int(target))
            v, f, col = even_resample(m.verts.detach(), m.faces, rs, attributes=m.color_logits.detach())
            kept = f.shape == m.faces.shape and torch.equal(f.to(m.faces.device), m.faces) and torch.equal(v, m.verts.detach())
            if not kept:
                break
        if not kept:  # else: refused (ResampleSettings.max_lost), the mesh and the optimiser's state stay as they are
            self._set_mesh(v, f, col)
        self._log({"phase": "eval", "step": self.step, "seconds": round(time.perf_counter() - self.t0, 3),
                   "what": "resample", "vertices_before": int(n0), "vertices_after": int(v.shape[0]), "kept": kept,
                   "method": None if kept else method})
        log.info("even resampling (%s): %d -> %d vertices%s", method, n0, v.shape[0],
                 " (not used: the mesh is kept)" if kept else "")

    def _set_mesh(self, verts: torch.Tensor, faces: torch.Tensor, color_logits: torch.Tensor) -> None:
        """Swap the canonical mesh; the optimiser keeps every other parameter's state (and all learning rates)."""
        from s3o_warp.kernels.regularisers import mesh_edges

        m = self.model
        m.verts = torch.nn.Parameter(verts.to(m.bone_centers).contiguous())
        m.color_logits = torch.nn.Parameter(color_logits.to(m.bone_centers).contiguous())
        m.faces = faces.to(device=m.bone_centers.device, dtype=torch.int64).contiguous()
        self.edges = mesh_edges(m.faces).to(self.device)
        self.lap_ref = m.verts.detach().clone()
        old = self.opt
        lrs = {g["name"]: g["lr"] for g in old.param_groups}
        self.opt = self._make_optimizer()
        for g in self.opt.param_groups:
            g["lr"] = lrs.get(g["name"], g["lr"])
            for p in g["params"]:
                if p in old.state:
                    self.opt.state[p] = old.state[p]
        self._good = None

    # -- checkpoints --------------------------------------------------------------------------------
    def state(self) -> dict:
        return {
            "version": CHECKPOINT_VERSION,
            "sequence": self.data.name,
            "num_frames": self.data.num_frames,
            "phase": self.phase,
            "step": self.step,
            "model": self.model.state_dict(),
            "optimizer": self.opt.state_dict(),
            "generator": self.gen.get_state(),
            "skeleton": self.skel.to_dict(),
            "lap_ref": self.lap_ref,
            "torch_rng": torch.get_rng_state(),
            "config": to_dict(self.cfg),
            "seconds": time.perf_counter() - self.t0,
            "pending_m_step": False,
        }

    def save_checkpoint(self) -> Path:
        ck = self.run_dir / "checkpoints"
        ck.mkdir(parents=True, exist_ok=True)
        idx = PHASES.index(self.phase) if self.phase in PHASES else len(PHASES)
        path = ck / f"step-{idx}-{self.phase}-{self.step:06d}.pt"
        _atomic_save(self.state(), path)
        kept = sorted(ck.glob("step-*.pt"), key=lambda p: p.stat().st_mtime)
        for old in kept[: -self.cfg.output.keep_checkpoints]:
            old.unlink(missing_ok=True)
        return path

    def save_branch_checkpoint(self) -> Path:
        """``checkpoints/branch.pt``: the state just before the first M-step that reads ``skeleton.t_o``, with that
        M-step pending, and ``checkpoints/branch.log.jsonl`` (the log up to here); ``fit(..., branch_from=run)``
        continues another t_o from it (:func:`fit`)."""
        ck = self.run_dir / "checkpoints"
        ck.mkdir(parents=True, exist_ok=True)
        st = self.state()
        st["pending_m_step"] = True
        path = ck / BRANCH_CHECKPOINT
        _atomic_save(st, path)
        _atomic_copy(self.log_file, ck / BRANCH_LOG)
        log.info("branch checkpoint before the first merge (joint step %d): %s", self.step, path)
        return path

    def _resize_bones(self, B: int) -> None:
        """Give the model B bones (values are overwritten by the checkpoint right after)."""
        m = self.model
        if m.num_bones == B:
            return
        T = m.num_frames
        kw = dict(dtype=m.bone_centers.dtype, device=m.bone_centers.device)
        m.bone_centers = torch.nn.Parameter(torch.zeros(B, 3, **kw))
        m.bone_quat = torch.nn.Parameter(torch.zeros(B, 4, **kw))
        m.bone_log_scales = torch.nn.Parameter(torch.zeros(B, 3, **kw))
        m.bone_aa = torch.nn.Parameter(torch.zeros(T, B, 3, **kw))
        m.bone_t = torch.nn.Parameter(torch.zeros(T, B, 3, **kw))

    def load_checkpoint(self, path: Path) -> None:
        st = torch.load(path, map_location=self.device, weights_only=False)
        _check_version(st, f"checkpoint {path}", "start a fresh run (drop --resume or use another --out)")
        if st.get("sequence") != self.data.name or st.get("num_frames") != self.data.num_frames:
            raise InputError(
                f"checkpoint {path} belongs to sequence '{st.get('sequence')}' ({st.get('num_frames')} frames), "
                f"not '{self.data.name}' ({self.data.num_frames} frames); use another --out or drop --resume"
            )
        pp = st["config"]["motion"]["principal_point"]
        if pp != self.cfg.motion.principal_point:
            raise InputError(f"checkpoint {path} was written with motion.principal_point={pp}, this fit has "
                             f"{self.cfg.motion.principal_point}; add --set motion.principal_point={pp} to continue it, "
                             "or start a fresh run")
        self._resize_bones(st["model"]["bone_centers"].shape[0])
        sm = st["model"]
        if sm["verts"].shape != self.model.verts.shape or sm["faces"].shape != self.model.faces.shape:
            self._set_mesh(sm["verts"], sm["faces"], sm["color_logits"])  # resampled mesh: values loaded below
        self.model.load_state_dict(st["model"])
        from s3o_warp.kernels.regularisers import mesh_edges

        self.edges = mesh_edges(self.model.faces).to(self.device)
        from s3o_warp.skeleton.mstep import SkeletonState

        self.skel = SkeletonState.from_dict(st["skeleton"])
        self.lap_ref = st["lap_ref"].to(self.device)
        self.phase, self.step = st["phase"], st["step"]
        if self.phase in PHASES:
            self.opt = self._make_optimizer()
            self.opt.load_state_dict(st["optimizer"])
        self.gen.set_state(st["generator"])
        torch.set_rng_state(st["torch_rng"])
        self._pending_m_step = bool(st.get("pending_m_step", False))
        self.t0 = time.perf_counter() - float(st.get("seconds", 0.0))  # log seconds count on from the checkpoint
        if self.log_file.exists():  # the log so far (the loss plot and the metrics' seconds cover the whole fit)
            self.history = [json.loads(line) for line in self.log_file.read_text().splitlines() if line.strip()]


def latest_checkpoint(run_dir: Path) -> Path | None:
    ck = Path(run_dir) / "checkpoints"
    files = sorted(ck.glob("step-*.pt"), key=lambda p: p.name) if ck.is_dir() else []
    return files[-1] if files else None


# ---------------------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------------------


def resolve_device(name: str | None) -> torch.device:
    """``None`` -> CUDA when Warp sees a GPU, else the CPU; ``cuda`` without CUDA -> one clear error."""
    import warp as wp

    from s3o_warp.kernels import _warp

    _warp.init()
    has_cuda = torch.cuda.is_available() and wp.get_cuda_device_count() > 0
    if name is None:
        return torch.device("cuda:0" if has_cuda else "cpu")
    if name.startswith("cuda"):
        if not has_cuda:
            raise InputError(f"--device {name}: no CUDA device is visible to Warp and torch here; use --device cpu")
        idx = int(name.split(":")[1]) if ":" in name else 0
        if idx >= torch.cuda.device_count():
            raise InputError(f"--device {name}: only {torch.cuda.device_count()} CUDA device(s); use cuda:0")
        return torch.device(f"cuda:{idx}")
    if name != "cpu":
        raise InputError(f"--device {name}: unknown device; use cpu, cuda or cuda:N")
    return torch.device("cpu")


def _check_writable(out_dir: Path) -> None:
    """The run directory (or its nearest existing parent) must be writable: one clear line otherwise."""
    p = out_dir
    while not p.exists() and p != p.parent:
        p = p.parent
    if not p.is_dir() or not os.access(p, os.W_OK):
        raise InputError(f"run directory {out_dir} is not writable ({p} is not a writable folder); choose another --out")


def fit(sequence_dir, out_dir, cfg: Config, device: torch.device, resume: bool = False, masks=None, name=None,
        branch_from=None) -> dict:
    """Fit one sequence and write the run directory; returns the metrics dict.

    ``sequence_dir`` is a sequence folder, a DAVIS root (with ``name``), a DAVIS sequence folder, or a
    video file / frame folder with a separate ``masks`` folder (see ``s3o_warp.data.sequence.open_sequence``).
    ``branch_from``: a finished or running fit of the same sequence whose settings differ from ``cfg`` only in
    ``skeleton.t_o``, ``t_u`` or ``t_d`` (:data:`BRANCH_MAY_DIFFER`: read only from the branch on); the fit starts from its ``checkpoints/branch.pt`` (the state just
    before the first merge) and its cached flow, so a t_o study pays for the shared part once (the rest of the run directory is this fit's own). With
    ``resume`` a checkpoint of ``out_dir`` itself comes first.
    """
    check(cfg)  # every setting, before anything is read or written
    out_dir = Path(out_dir)
    _check_writable(out_dir)
    branch = _branch_checkpoint(Path(branch_from), out_dir, cfg) if branch_from is not None else None
    if branch is not None:
        _link_cache(Path(branch_from) / "cache", out_dir / "cache")
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    data = prepare_data(Path(sequence_dir), cfg, out_dir, device, masks=masks, name=name)  # validates input first
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"run directory {out_dir} cannot be created ({e.strerror}); choose another --out") from None
    save_toml(cfg, out_dir / "config.toml")
    with repeatable(cfg.repeatable and device.type == "cpu"):
        coarse_res = coarse_model(data, cfg)
        fitter = Fitter(data, coarse_res, cfg, out_dir, device)
        ck = latest_checkpoint(out_dir) if resume else None
        if resume and ck is None and branch is None:
            log.warning("--resume: no checkpoint in %s, starting from the beginning", out_dir / "checkpoints")
        if ck is None and branch is not None:
            ck = branch
            _atomic_copy(branch.with_name(BRANCH_LOG), out_dir / "log.jsonl")
        if ck is not None:
            log.info("resuming from %s", ck)
            fitter.load_checkpoint(ck)
        elif (out_dir / "log.jsonl").exists():
            (out_dir / "log.jsonl").unlink()
        if fitter.phase != "done":
            with _stop_on_signals(fitter):
                fitter.run()
        return write_outputs(fitter)


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _check_version(state: dict, what: str, fix: str) -> None:
    """InputError, one line naming ``what`` and the ``fix``, unless ``state`` is a checkpoint of this format."""
    v = state.get("version")
    if v != CHECKPOINT_VERSION:
        age = "an earlier" if v is None or (isinstance(v, int) and v < CHECKPOINT_VERSION) else "another"
        raise InputError(f"{what} was written by {age} version of s3o-warp (checkpoint version {v}, this one reads "
                         f"{CHECKPOINT_VERSION}) and must be refit: {fix}")


def _branch_checkpoint(parent: Path, out_dir: Path, cfg: Config) -> Path:
    """The branch checkpoint of run ``parent`` for a fit with ``cfg`` into ``out_dir``; InputError when it is
    missing or the settings differ in more than :data:`BRANCH_MAY_DIFFER`."""
    ck = parent / "checkpoints" / BRANCH_CHECKPOINT
    if parent.resolve() == out_dir.resolve():
        raise InputError(f"--branch-from {parent}: that is the run directory itself; choose another --out")
    if not ck.is_file():
        raise InputError(f"--branch-from {parent}: no {ck.relative_to(parent)} there (it is written just before the "
                         "first merge of a fit with skeleton.method=s3o, skeleton.epochs >= skeleton.e1 + 3 and "
                         "output.branch_checkpoint=true); fit that run first or drop --branch-from")
    st = torch.load(ck, map_location="cpu", weights_only=False)
    _check_version(st, f"--branch-from {parent}: its {ck.relative_to(parent)}", "refit that run, then branch from it")
    theirs = _flat(st["config"])
    ours = _flat(to_dict(cfg))
    free = set(BRANCH_MAY_DIFFER) | {"preset"}
    differ = sorted(k for k in set(theirs) | set(ours)
                    if k not in free and not k.startswith("output.") and theirs.get(k) != ours.get(k))
    if differ:
        shown = ", ".join(f"{k} ({theirs.get(k)!r} there, {ours.get(k)!r} here)" for k in differ[:4])
        raise InputError(f"--branch-from {parent}: its settings differ in {shown}{' ...' if len(differ) > 4 else ''}; "
                         f"only {', '.join(BRANCH_MAY_DIFFER)} may differ, fit afresh for the others")
    return ck


def _link_cache(src: Path, dst: Path) -> None:
    """The parent run's cached flow for a branched fit: hard links (a copy across file systems). The flow files
    are written once under a temporary name and renamed, so neither run ever writes into the other's; the crops'
    memory map (long sequences) is rewritten by each run and not shared."""
    import shutil

    if not src.is_dir():
        return
    for f in src.glob("flow_*.npy"):
        t = dst / f.name
        if t.exists():
            continue
        t.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(f, t)
        except OSError:
            shutil.copy2(f, t)


@contextlib.contextmanager
def repeatable(enabled: bool = True):
    """Torch's deterministic algorithms inside the block (``cfg.repeatable``), the caller's setting restored after.

    On the CPU the backward of indexing (``index_put_`` with ``accumulate=True``) otherwise sums in the
    order its threads finish, so two runs of one seed part in the last bits and then for good.
    """
    if not enabled:
        yield
        return
    was, warn = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(was, warn_only=warn)


class _stop_on_signals:
    """SIGINT / SIGTERM during the loop -> checkpoint at the step boundary, then FitInterrupted."""

    def __init__(self, fitter: Fitter):
        self.fitter = fitter
        self.old = {}

    def __enter__(self):
        import signal
        import threading

        if threading.current_thread() is not threading.main_thread():
            return self
        for sig in (signal.SIGINT, signal.SIGTERM):
            self.old[sig] = signal.getsignal(sig)
            signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame):
        log.warning("signal %d: writing a checkpoint and stopping after this step", signum)
        self.fitter.request_stop()

    def __exit__(self, *exc):
        import signal

        for sig, h in self.old.items():
            signal.signal(sig, h)
        return False


def write_outputs(fitter: Fitter) -> dict:
    """Rig files, metrics and renders of a finished fit."""
    from s3o_warp.run import outputs

    return outputs.write_run(fitter)
