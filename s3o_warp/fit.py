"""The loop of Algorithm 1: the coarse phase, the warm-up and the joint phase, with the M-step and the even
resampling between the joint phase's epochs, then the run directory.

``fit(sequence_dir, out_dir, cfg, device)`` checks every setting, reads the sequence and its flow
(:mod:`s3o_warp.data.store`), builds the coarse model (:mod:`s3o_warp.coarse.model`) and runs :class:`Fitter`:

- coarse: the shape on the canonical frame (:func:`s3o_warp.coarse.model.coarse_terms`);
- warm-up: camera and motion with the mesh frozen, after the camera hypotheses (:mod:`s3o_warp.motion.hypotheses`);
- joint: shape, colour, camera and motion (the E-step, :func:`s3o_warp.motion.objective.motion_terms`), and after
  each epoch but the last the M-step (:func:`s3o_warp.skeleton.mstep.m_step`) and the even resampling (paper B).

The loop owns the optimisers (named parameter groups), the frame windows, the NaN guard, logging, checkpoints
and stopping; it computes no loss itself. Checkpoints are written at phase boundaries and every
``output.checkpoint_every`` steps (:mod:`s3o_warp.run.checkpoint`); ``resume=True`` continues from the last one,
``branch_from`` from another run's branch checkpoint (:mod:`s3o_warp.run.branch`).
"""

from __future__ import annotations

import contextlib
import copy
import json
import logging
import math
import os
import resource
import time
from pathlib import Path

import numpy as np
import torch
import warp as wp
from tqdm import tqdm

from s3o_warp import interrupt, resample
from s3o_warp.coarse.model import (
    COARSE_SIGMA,
    COARSE_SIGMA_FINAL,
    CoarseResult,
    coarse_model,
    coarse_terms,
    refit_bones_to_parts,
)
from s3o_warp.config import Config, check, to_dict, to_toml
from s3o_warp.data.io import copy_file, write_text
from s3o_warp.data.store import FitData, prepare_data
from s3o_warp.errors import InputError
from s3o_warp.evaluation.views import body_width_ratio, mesh_smoothness
from s3o_warp.kernels import _warp
from s3o_warp.model import S3OModel
from s3o_warp.motion import objective
from s3o_warp.motion.crossings import resolve_model_crossings
from s3o_warp.motion.hypotheses import Search, select_hypotheses
from s3o_warp.motion.large_steps import FitAdam
from s3o_warp.motion.losses import soft_iou
from s3o_warp.motion.windows import FrameWindows
from s3o_warp.ops import mesh_edges
from s3o_warp.run import outputs
from s3o_warp.run.branch import BRANCH_LOG, branch_checkpoint, link_cache, save_branch
from s3o_warp.run.checkpoint import (
    CHECKPOINT_VERSION,
    check_version,
    load_newest,
    save_step,
)
from s3o_warp.run.resume import apply_changed_settings
from s3o_warp.skeleton.mstep import (
    SkeletonState,
    m_step,
    prune_empty_bones,
    refresh_joints,
    virtual_bones_init,
)

log = logging.getLogger(__name__)

PHASES = ("coarse", "warmup", "joint")

NAN_LR_FACTOR = 0.5
"""On a NaN/Inf loss or gradient: skip the step, roll back to the last good state, scale learning rates by this."""
NAN_MAX_CONSECUTIVE = 5
"""Stop the fit (naming the loss term) after this many NaN/Inf steps in a row."""
SNAPSHOT_EVERY = 10
"""Keep an in-memory copy of the last good state every this many steps (the NaN roll-back target)."""


class FitDiverged(InputError):
    """The loss or its gradient stayed NaN/Inf for several steps in a row; the message names the term."""


class FitInterrupted(interrupt.Interrupted):
    """Raised after a stop request (Ctrl-C, SIGTERM) once the checkpoint of the current step is written."""


class Fitter:
    """Runs the phases with one Adam optimiser per phase, logging and atomic checkpoints."""

    def __init__(self, data: FitData, coarse_res: CoarseResult, cfg: Config, run_dir: Path, device):
        self.data, self.cfg, self.run_dir, self.device = data, cfg, Path(run_dir), device
        check(cfg)  # a Config built in code, not by make_config: refused before any work
        self.coarse = coarse_res
        self.model = S3OModel(coarse_res.init).to(device)
        v0 = self.model.verts.detach()
        self.ctx = objective.TermContext(
            edges=mesh_edges(self.model.faces).to(device),
            lap_ref=v0.clone(),  # reference shape of the relative Laplacian term
            sym_plane=(torch.as_tensor(coarse_res.sym_plane[0], device=device), coarse_res.sym_plane[1]),
            size=float((v0.max(0).values - v0.min(0).values).norm()),  # the object's size (bbox diagonal)
        )
        videos = None
        if data.num_videos > 1:  # no smoothness across two videos (nor across the rows synchronized ones share)
            videos = [(v.start, v.stop) for v in data.videos]
            self.ctx.frame_pairs = torch.as_tensor(data.pair_valid(1), device=device)
            if not cfg.motion.synchronized:
                self.ctx.motion_pairs = self.ctx.frame_pairs
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.windows = FrameWindows(data.num_frames, cfg.motion.batch_frames, coarse_res.canonical, self.gen, device,
                                    videos=videos, anchors=list(coarse_res.anchors) or None)
        self.phase = PHASES[0]
        self.step = 0  # step within the phase
        self.log_file = self.run_dir / "log.jsonl"
        self.t0 = time.perf_counter()
        self.history: list[dict] = []
        self.opt = self.make_optimizer()
        self._hypotheses: Search | None = None  # a search read from a checkpoint taken inside it
        self._bad = 0
        self._pending_m_step = False  # a branch checkpoint was loaded: its M-step runs before the next step
        self._good = None
        parents = np.asarray(coarse_res.parents, np.int64)
        if cfg.skeleton.method == "virtual":
            parents = virtual_bones_init(self.model, cfg)
            self.opt = self.make_optimizer()
        self.skel = SkeletonState(parents=parents)
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

    def request_stop(self) -> None:
        """Ask the loop to checkpoint and stop at the next step boundary (safe from a signal handler)."""
        interrupt.request()

    def stop_point(self, hypotheses: Search | None = None) -> None:
        """A point the fit can continue from (a step boundary, or one inside the camera ``hypotheses``): when a stop
        was requested, its checkpoint is written and FitInterrupted raised."""
        if not interrupt.requested():
            return
        path = self.save_checkpoint(hypotheses)
        where = f"{self.phase} step {self.step}" if hypotheses is None else f"the camera hypotheses ({hypotheses.where()})"
        raise FitInterrupted(f"stopped at {where}; checkpoint {path}")

    # -- optimiser per phase: named parameter groups ------------------------------------------------
    def make_optimizer(self) -> torch.optim.Optimizer:
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
        if self.phase == "joint":  # Laplacian-preconditioned shape steps with a uniform second moment
            return FitAdam(groups, m.faces, mc.shape_smoothing)
        return torch.optim.Adam(groups)

    def phase_steps(self, phase: str) -> int:
        mc = self.cfg.motion
        return {"coarse": self.cfg.coarse.steps, "warmup": mc.warmup_steps, "joint": mc.steps}[phase]

    # -- the objective of each phase ----------------------------------------------------------------
    def coarse_losses(self) -> tuple[dict, torch.Tensor, torch.Tensor]:
        sigma = objective.decayed_sigma(COARSE_SIGMA, COARSE_SIGMA_FINAL, self.step, self.phase_steps(self.phase))
        return coarse_terms(self.model, self.data, self.coarse, self.cfg.coarse, sigma, self.ctx)

    def motion_losses(self, frames: torch.Tensor) -> tuple[dict, torch.Tensor, torch.Tensor]:
        mc = self.cfg.motion
        self.ctx.joints = self._joint_tensors()
        sigma = objective.decayed_sigma(mc.sigma, mc.sigma_final, self.step, self.phase_steps(self.phase))
        return objective.motion_terms(self.model, self.data, frames, mc, joint_phase=self.phase == "joint",
                                      sigma=sigma, ctx=self.ctx)

    def mean_terms(self, span: tuple[int, int] | None = None) -> dict[str, float]:
        """Every weighted motion term averaged over windows that cover every frame (of ``span``, one video's
        ``(start, stop)``), no step taken."""
        return objective.mean_terms(self.motion_losses, self.data.num_frames, self.cfg.motion.batch_frames,
                                    self.device, span=span)

    def flow_by_gap(self, span: tuple[int, int] | None = None) -> dict[int, float]:
        """The flow error over every pair of every gap (:func:`objective.flow_by_gap`; of ``span``, one video's
        ``(start, stop)``), no step taken."""
        return objective.flow_by_gap(self.model, self.data, self.cfg.motion.batch_frames, span=span)

    @property
    def reference_video(self) -> int:
        """The video of the canonical frame: the others are registered to it."""
        return self.windows.video(self.coarse.canonical)

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

    def surface(self) -> dict[str, float]:
        """The canonical mesh's smoothness and roundness (roughness, normal consistency, width ratio across the
        lift's symmetry plane), logged with every step record so a reader sees where a fit crumples or flattens."""
        v = self.model.verts.detach().cpu().numpy()
        normal, offset = self.ctx.sym_plane
        return {**mesh_smoothness(v, self.model.faces.cpu().numpy()),
                "width_ratio": body_width_ratio(v, normal.cpu().numpy(), float(offset))}

    def hard_iou(self) -> float:
        return objective.hard_iou(self.model, self.data, self.cfg.motion.batch_frames)

    def record(self, rec: dict) -> None:
        """Append ``rec`` to the log (``log.jsonl`` and :attr:`history`); evaluation records get the peak memory."""
        if rec.get("phase") == "eval":
            rec["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
        self.history.append(rec)
        with open(self.log_file, "a") as fh:
            fh.write(json.dumps(rec) + "\n")

    def _event(self, what: str, **fields) -> None:
        self.record({"phase": "eval", "step": fields.pop("step", self.step),
                     "seconds": round(time.perf_counter() - self.t0, 3), "what": what, **fields})

    # -- loop ---------------------------------------------------------------------------------------
    def run(self) -> None:
        if self.phase == PHASES[0] and self.step == 0:
            self._event("initial", step=0, iou_all_frames=self.hard_iou())
        for phase in PHASES[PHASES.index(self.phase):]:
            if phase != self.phase:
                if self.phase == "coarse" and self.cfg.skeleton.method == "s3o":
                    refit_bones_to_parts(self.model, self.coarse)
                if phase == "joint" and self.cfg.motion.resolve_crossings:
                    self.resolve_crossings()
                self.phase, self.step = phase, 0
                self.opt = self.make_optimizer()
                self.ctx.lap_ref = self.model.verts.detach().clone()
                self._good = None
                self.save_checkpoint()
            n = self.phase_steps(phase)
            if phase == "warmup" and self.step == 0 and (self.cfg.motion.hypotheses > 1 or self.data.num_videos > 1
                                                         or self.cfg.motion.turn_rate is not None):
                select_hypotheses(self, self._hypotheses)
                self._hypotheses = None
            with tqdm(total=n, initial=self.step, desc=f"{phase:>6}", dynamic_ncols=True, leave=True) as bar:
                self._run_phase(phase, n, bar)
        self._event("final", step=0, iou_all_frames=self.hard_iou())
        if self.phase != "done":
            self.final_skeleton()
        self.phase, self.step = "done", 0
        self.save_checkpoint()

    def _run_phase(self, phase: str, n: int, bar: tqdm) -> None:
        """The steps of ``phase`` from :attr:`step` to ``n`` (the M-steps at the joint phase's epoch ends)."""
        if self._pending_m_step:  # branched from another run's branch checkpoint: its M-step, with this t_o
            self._pending_m_step = False
            self._m_step(n)
        while self.step < n:
            self.opt.zero_grad(set_to_none=True)
            frames = None
            if phase == "coarse":
                terms, sil, mask = self.coarse_losses()
            else:
                frames = self.windows.next(phase == "warmup", self.step, self.cfg.motion.warmup_steps,
                                            self.model)
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
            self.step_window(frames)
            self.step += 1
            self._bad = 0
            if self.step % SNAPSHOT_EVERY == 0 or self._good is None:
                self._snapshot()
            bar.update(1)
            if self.step % self.cfg.motion.log_every == 0 or self.step == n:
                iou = float(soft_iou(sil.detach(), mask).mean())
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
                    "surface": self.surface(),
                }
                self.record(rec)
                bar.set_postfix(loss=f"{float(total):.4f}", iou=f"{iou:.3f}")
            if phase == "joint" and self._epoch_end(n):
                if self.cfg.motion.resolve_crossings and self.step == self.steps_per_epoch(n):
                    # once more when the legs fit better than after the warm-up, with the lift's bones (before
                    # any M-step)
                    self.resolve_crossings()
                if self.cfg.output.branch_checkpoint and self.is_branch_point(n):
                    self.save_branch_checkpoint()
                before = copy.deepcopy({**self.state(), "pending_m_step": True})
                try:
                    self._m_step(n)
                except interrupt.Interrupted as e:  # inside the M-step or the resampling: resumed, it runs again
                    path = self.save_checkpoint(state=before)
                    raise FitInterrupted(f"stopped at {phase} step {self.step} ({e}); checkpoint {path}") from None
            self.stop_point()
            if self.step % self.cfg.output.checkpoint_every == 0 and self.step < n:
                self.save_checkpoint()

    def final_skeleton(self) -> None:
        """The shape moved since the last M-step: bones left owning no vertex go (not in the paper), and the joints
        are placed on the final mesh."""
        sc = self.cfg.skeleton
        if not (sc.method == "s3o" and prune_empty_bones(self.model, self.opt, self.skel, sc)):
            refresh_joints(self.model, self.skel, sc)

    def resolve_crossings(self) -> list[int]:
        """Paired limbs swing through their crossings instead of bouncing (:mod:`s3o_warp.motion.crossings`); logs
        and returns the number of exchanged frames per pair."""
        m = self.model
        virtual = self.cfg.skeleton.method == "virtual"  # k-means bones: the lift's pairs do not apply
        pairs = [] if virtual else [p for p in self.coarse.limb_pairs if max(p.a, p.b) < m.num_bones]
        videos = None
        if self.data.num_videos > 1:  # each video on its own, the reference first
            w = self.windows
            order = [self.reference_video] + [v for v in range(len(w.videos)) if v != self.reference_video]
            videos = [(*w.videos[v], w.anchors[v]) for v in order]
        counts = resolve_model_crossings(m, self.opt, pairs, self.coarse.canonical, videos)
        self._event("crossings", pairs=[[p.a, p.b] for p in pairs], exchanged_frames=counts)
        log.info("crossings: %d limb pairs, exchanged frames %s", len(pairs), counts)
        return counts

    def step_window(self, frames: torch.Tensor | None) -> None:
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
        keep_rows = keep
        if m.num_motion_rows != m.num_frames:  # synchronized videos: the rows of the window's frames move
            keep_rows = torch.ones(m.num_motion_rows, dtype=torch.bool, device=frames.device)
            keep_rows[m.motion_of[frames]] = False
        per_frame = ((m.root_aa, keep), (m.root_t, keep), (m.bone_aa, keep_rows), (m.bone_t, keep_rows)) + (
            () if m.pp_shared else ((m.pp, keep),))
        saved = [p.data.clone() for p, _ in per_frame]
        self.opt.step()
        for (p, k), v in zip(per_frame, saved):  # where(), not a boolean index: no host sync on a GPU
            p.data.copy_(torch.where(k.view(-1, *([1] * (p.dim() - 1))), v, p.data))

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
        epoch = self.step // self.steps_per_epoch(n) - 1
        if m_step(self.model, self.opt, self.data, self.cfg, self.skel, epoch):
            self._good = None  # shapes changed: the NaN roll-back target is taken anew
        every = self.cfg.motion.resample_epochs
        if every > 0 and (epoch + 1) % every == 0:
            self.resample_mesh()

    @torch.no_grad()
    def resample_mesh(self) -> None:
        """Even resampling (paper B): same surface, uniform vertices; colours carried, skinning follows the bones."""
        m = self.model
        target = self.cfg.motion.resample_vertices or len(self.coarse.init.verts)
        n0 = m.verts.shape[0]
        for method in resample.METHODS:
            if method != resample.METHODS[0]:
                log.info("even resampling: trying %s on the same mesh", method)
            rs = resample.ResampleSettings(method=method, target_vertices=int(target))
            v, f, col = resample.even_resample(m.verts.detach(), m.faces, rs, attributes=m.color_logits.detach())
            kept = f.shape == m.faces.shape and torch.equal(f.to(m.faces.device), m.faces) and torch.equal(v, m.verts.detach())
            if not kept:
                break
        if not kept:  # else: refused (ResampleSettings.max_lost), the mesh and the optimiser's state stay as they are
            self._set_mesh(v, f, col)
        self._event("resample", vertices_before=int(n0), vertices_after=int(v.shape[0]), kept=kept,
                    method=None if kept else method)
        log.info("even resampling (%s): %d -> %d vertices%s", method, n0, v.shape[0],
                 " (not used: the mesh is kept)" if kept else "")

    def _set_mesh(self, verts: torch.Tensor, faces: torch.Tensor, color_logits: torch.Tensor) -> None:
        """Swap the canonical mesh; the optimiser keeps every other parameter's state (and all learning rates)."""
        m = self.model
        m.verts = torch.nn.Parameter(verts.to(m.bone_centers).contiguous())
        m.color_logits = torch.nn.Parameter(color_logits.to(m.bone_centers).contiguous())
        m.faces = faces.to(device=m.bone_centers.device, dtype=torch.int64).contiguous()
        self.ctx.edges = mesh_edges(m.faces).to(self.device)
        self.ctx.lap_ref = m.verts.detach().clone()
        old = self.opt
        lrs = {g["name"]: g["lr"] for g in old.param_groups}
        self.opt = self.make_optimizer()
        for g in self.opt.param_groups:
            g["lr"] = lrs.get(g["name"], g["lr"])
            for p in g["params"]:
                if p in old.state:
                    self.opt.state[p] = old.state[p]
        self._good = None

    def _apply_new_rates(self, saved: dict) -> None:
        """A learning rate set otherwise than in the checkpoint's settings (``--resume --set motion.lr_shape=...``)
        goes into its optimiser group; the others keep the checkpoint's (which the NaN guard may have lowered)."""
        keys = {"motion": "lr_motion", "camera": "lr_camera", "color": "lr_color", "bones": "lr_bones",
                "shape": "lr_shape"}
        for g in self.opt.param_groups:
            section, key = ("coarse", "lr") if self.phase == "coarse" else ("motion", keys.get(g.get("name"), ""))
            new, old = getattr(getattr(self.cfg, section), key, None), saved.get(section, {}).get(key)
            if new is not None and old is not None and new != old:
                log.info("resume: %s.%s %g (the checkpoint's %g) applied to the '%s' group", section, key, new, old,
                         g["name"])
                g["lr"] = new

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
            "lap_ref": self.ctx.lap_ref,
            "torch_rng": torch.get_rng_state(),
            "config": to_dict(self.cfg),
            "seconds": time.perf_counter() - self.t0,
            "pending_m_step": False,
        }

    def save_checkpoint(self, hypotheses: Search | None = None, state: dict | None = None) -> Path:
        """The checkpoint of the current step (``state``, else :meth:`state`); one taken inside the camera
        ``hypotheses`` is the warm-up's step 0 with the search (its model and optimiser are the hypothesis in
        training)."""
        idx = PHASES.index(self.phase) if self.phase in PHASES else len(PHASES)
        st, step = state or self.state(), self.step
        if hypotheses is not None:
            st["step"] = step = 0
            st["hypotheses"] = hypotheses.state_dict()
        return save_step(self.run_dir, st, idx, self.phase, step, self.cfg.output.keep_checkpoints)

    def save_branch_checkpoint(self) -> Path:
        """The state just before the first M-step that reads ``skeleton.t_o`` (:mod:`s3o_warp.run.branch`)."""
        path = save_branch(self.run_dir, self.state(), self.log_file)
        log.info("branch checkpoint before the first merge (joint step %d): %s", self.step, path)
        return path

    def _resize_bones(self, B: int) -> None:
        """Give the model B bones (values are overwritten by the checkpoint right after)."""
        m = self.model
        if m.num_bones == B:
            return
        T = m.num_motion_rows
        kw = dict(dtype=m.bone_centers.dtype, device=m.bone_centers.device)
        m.bone_centers = torch.nn.Parameter(torch.zeros(B, 3, **kw))
        m.bone_quat = torch.nn.Parameter(torch.zeros(B, 4, **kw))
        m.bone_log_scales = torch.nn.Parameter(torch.zeros(B, 3, **kw))
        m.bone_aa = torch.nn.Parameter(torch.zeros(T, B, 3, **kw))
        m.bone_t = torch.nn.Parameter(torch.zeros(T, B, 3, **kw))

    def load_checkpoint(self, path: Path, st: dict | None = None) -> None:
        """Continue from the checkpoint at ``path`` (``st``: its state, when already read)."""
        if st is None:
            st = torch.load(path, map_location=self.device, weights_only=False)
        check_version(st, f"checkpoint {path}", "start a fresh run (drop --resume or use another --out)")
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
        self.ctx.edges = mesh_edges(self.model.faces).to(self.device)
        self.skel = SkeletonState.from_dict(st["skeleton"])
        self.ctx.lap_ref = st["lap_ref"].to(self.device)
        self.phase, self.step = st["phase"], st["step"]
        if self.phase in PHASES:
            self.opt = self.make_optimizer()
            if "hypotheses" in st:  # taken inside the search: the optimiser is the hypothesis'
                self._hypotheses = Search.from_state(st["hypotheses"], st["optimizer"])
            else:
                self.opt.load_state_dict(st["optimizer"])
                self._apply_new_rates(st["config"])
        self.gen.set_state(st["generator"])
        torch.set_rng_state(st["torch_rng"])
        self._pending_m_step = bool(st.get("pending_m_step", False))
        self.t0 = time.perf_counter() - float(st.get("seconds", 0.0))  # log seconds count on from the checkpoint
        if self.log_file.exists():  # the log so far (the loss plot and the metrics' seconds cover the whole fit)
            self.history = [json.loads(line) for line in self.log_file.read_text().splitlines() if line.strip()]



# ---------------------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------------------


def resolve_device(name: str | None) -> torch.device:
    """``None`` -> CUDA when Warp sees a GPU, else the CPU; ``cuda`` without CUDA -> one clear error (with Warp's
    missing-driver line, which is not printed otherwise)."""
    _warp.init()
    has_cuda = torch.cuda.is_available() and wp.get_cuda_device_count() > 0
    if name is None:
        return torch.device("cuda:0" if has_cuda else "cpu")
    if name.startswith("cuda"):
        if not has_cuda:
            why = f" (Warp: {_warp.driver_warning.removeprefix('Warp CUDA warning: ').rstrip('.')})" if _warp.driver_warning else ""
            raise InputError(f"--device {name}: no CUDA device is visible to Warp and torch here{why}; use --device cpu")
        idx = int(name.split(":")[1]) if ":" in name else 0
        if idx >= torch.cuda.device_count():
            raise InputError(f"--device {name}: only {torch.cuda.device_count()} CUDA device(s); use cuda:0")
        return torch.device(f"cuda:{idx}")
    if name != "cpu":
        raise InputError(f"--device {name}: unknown device; use cpu, cuda or cuda:N")
    return torch.device("cpu")


def check_writable(out_dir: Path) -> None:
    """The run directory (or its nearest existing parent) must be writable: one clear line otherwise."""
    p = out_dir
    while not p.exists() and p != p.parent:
        p = p.parent
    if not p.is_dir() or not os.access(p, os.W_OK):
        raise InputError(f"run directory {out_dir} is not writable ({p} is not a writable folder); choose another --out")


def fit(sequence_dir, out_dir, cfg: Config, device: torch.device, resume: bool = False, masks=None, name=None,
        branch_from=None) -> dict:
    """Fit one sequence, or one object from several (``sequence_dir`` and ``masks`` lists), and write the run
    directory; returns the metrics dict (several videos: ``{"videos": {name: metrics}, "mean", "registration"}``).

    ``sequence_dir`` is a sequence folder, a DAVIS root (with ``name``), a DAVIS sequence folder, or a
    video file / frame folder with a separate ``masks`` folder (see ``s3o_warp.data.sequence.open_sequence``).
    ``branch_from``: a finished or running fit of the same sequence whose settings differ from ``cfg`` only in
    ``skeleton.t_o``, ``t_u`` or ``t_d`` (:data:`s3o_warp.run.branch.BRANCH_MAY_DIFFER`: read only from the branch on); the fit starts from its ``checkpoints/branch.pt`` (the state just
    before the first merge) and its cached flow, so a t_o study pays for the shared part once (the rest of the run directory is this fit's own). With
    ``resume`` a checkpoint of ``out_dir`` itself comes first: the newest that can be read
    (:func:`s3o_warp.run.checkpoint.load_newest`), with the settings changed since it applied or refused before any
    work (:mod:`s3o_warp.run.resume`).
    """
    check(cfg)  # every setting, before anything is read or written
    out_dir = Path(out_dir)
    check_writable(out_dir)
    branch = branch_checkpoint(Path(branch_from), out_dir, cfg) if branch_from is not None else None
    if branch is not None:
        link_cache(Path(branch_from) / "cache", out_dir / "cache")
    with interrupt.on_signals():  # Ctrl-C, SIGTERM: every long loop below stops at its next check
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed)
        resumed = load_newest(out_dir, device) if resume else None  # (path, state); damaged ones passed over
        if resumed is not None:
            apply_changed_settings(resumed[1], cfg, resumed[0])  # one that cannot take effect: refused here
        dirs = [Path(p) for p in sequence_dir] if isinstance(sequence_dir, (list, tuple)) else [Path(sequence_dir)]
        if len(dirs) > 1 and cfg.motion.principal_point == "shared":
            raise InputError("motion.principal_point=shared takes one video; fit several videos with "
                             "motion.principal_point=frame (the default)")
        data = prepare_data(dirs if len(dirs) > 1 else dirs[0], cfg, out_dir, device, masks=masks, name=name)
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise InputError(f"run directory {out_dir} cannot be created ({e.strerror}); choose another --out") from None
        write_text(out_dir / "config.toml", to_toml(cfg))
        with repeatable(cfg.repeatable and device.type == "cpu"):
            coarse_res = coarse_model(data, cfg)
            fitter = Fitter(data, coarse_res, cfg, out_dir, device)
            ck, st = resumed or (None, None)
            if resume and ck is None and branch is None:
                log.warning("--resume: no checkpoint in %s, starting from the beginning", out_dir / "checkpoints")
            if ck is None and branch is not None:
                ck = branch
                copy_file(branch.with_name(BRANCH_LOG), out_dir / "log.jsonl")
            if ck is not None:
                log.info("resuming from %s", ck)
                fitter.load_checkpoint(ck, st)
            elif (out_dir / "log.jsonl").exists():
                (out_dir / "log.jsonl").unlink()
            if fitter.phase != "done":
                fitter.run()
            return outputs.write_run(fitter)


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

