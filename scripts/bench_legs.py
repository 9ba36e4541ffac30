#!/usr/bin/env python
"""Where the legs are lost: PCK-T by role after each phase of a fit, written to ``benchmarks/legs-<device>.json``.

    python scripts/bench_legs.py --cases horse dog [fox120 deer husky cows robot] [--seeds 0] [--out-dir DIR]
                                 [--set key=value ...] [--rescore]

Each case is fitted as ``scripts/bench_fit.py`` fits it (the same sequences, settings and run folder names), with a
checkpoint kept at every phase boundary and every epoch end of the joint phase. Every checkpoint is then scored as
a finished fit would be (:func:`s3o_warp.evaluation.report.evaluate_run` on its rig): mask IoU, PCK-T, the limbs'
ends against the rest and the side facing the camera against the far side (``pck_t.groups``), the worst keypoints,
and on synthetic sequences where the surface under each side's keypoints lies (:func:`keypoint_depths`). A
checkpoint at an epoch end holds the state after that epoch's M-step and resampling, so its mask IoU is below the
next epoch's. ``--rescore`` scores the runs already in ``--out-dir`` without fitting.

Phases (the checkpoint names): ``coarse`` (the lift after the coarse fit, every frame in the canonical pose),
``warmup`` (after the camera hypotheses, the warm-up and the first crossing pass), ``epoch N`` (the joint phase's
epoch N and its M-step), ``done``.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_fit import command_line, prepare_case, record  # noqa: E402

from s3o_warp.coarse.model import coarse_model  # noqa: E402
from s3o_warp.config import make_config  # noqa: E402
from s3o_warp.data.store import prepare_data  # noqa: E402
from s3o_warp.evaluation.image import render_frames, surface_under_keypoints  # noqa: E402
from s3o_warp.evaluation.keypoints import counterparts, keypoint_roles  # noqa: E402
from s3o_warp.evaluation.loaders import load_ground_truth, load_keypoints, load_predictions  # noqa: E402
from s3o_warp.evaluation.report import _pair_frames, evaluate_run  # noqa: E402
from s3o_warp.evaluation.shape import frame_similarities, shape_metrics  # noqa: E402
from s3o_warp.export.rig import save_rig  # noqa: E402
from s3o_warp.fit import Fitter, fit, repeatable, resolve_device  # noqa: E402
from s3o_warp.provenance import REPO, cpu_name, git_commit, versions  # noqa: E402
from s3o_warp.run.outputs import rig_from_model  # noqa: E402

log = logging.getLogger("bench_legs")

GROUPS = ("ends", "rest", "near", "far", "ends_near", "ends_far")
def keypoint_depths(points: np.ndarray, own: np.ndarray, other: np.ndarray, near: np.ndarray, end: np.ndarray) -> dict:
    """Where the fitted surface under each side keypoint lies in depth, by role: per group (``ends_near``,
    ``ends_far``, ``rest_near``, ``rest_far``) the keypoints counted (``n``), the share whose surface point lies
    nearer the other side's true keypoint than its own (``other_leg``: the pixel was given to the other limb) and
    the median depth offset from the true keypoint as a share of the pair's true depth separation (``depth_share``,
    towards the other side positive: 1 = at the other limb's depth).

    Args:
        points: (M, 3) the surface points under the keypoints, camera space, each frame aligned on its own.
        own, other: (M, 3) the true keypoint and its other-side counterpart, camera space.
        near: (M,) bool, the keypoint's side faces the camera (its true depth is the smaller).
        end: (M,) bool, the keypoint is a limb's end.
    """
    p, g, o = (np.asarray(a, np.float64) for a in (points, own, other))
    sep = o[:, 2] - g[:, 2]
    share = np.where(np.abs(sep) > 1e-9, (p[:, 2] - g[:, 2]) / np.where(np.abs(sep) > 1e-9, sep, 1.0), np.nan)
    closer = np.linalg.norm(p - o, axis=1) < np.linalg.norm(p - g, axis=1)
    out = {}
    for role, rsel in (("ends", end), ("rest", ~end)):
        for side, ssel in (("near", near), ("far", ~near)):
            sel = np.asarray(rsel, bool) & np.asarray(ssel, bool)
            n = int(sel.sum())
            out[f"{role}_{side}"] = {"n": n, "other_leg": float(closer[sel].mean()) if n else None,
                                     "depth_share": float(np.nanmedian(share[sel])) if n and np.isfinite(share[sel]).any()
                                     else None}
    return out


def surface_depths(run: Path, seq: Path) -> dict | None:
    """:func:`keypoint_depths` of a run on a synthetic sequence (None without ground-truth keypoints): each annotated
    frame's visible side keypoints, the surface point under each (LASR's nearest-foreground-pixel rule), each frame
    aligned on its own (the sequence's similarity, then ICP on that frame)."""
    gt_dir, kp_file = seq / "ground_truth", seq / "keypoints.json"
    if not gt_dir.is_dir() or not kp_file.is_file():
        return None
    pred, gt, kps = load_predictions(run), load_ground_truth(gt_dir), load_keypoints(kp_file)
    if not gt.keypoints or any(n not in gt.keypoints for n in kps.names):
        return None
    pi, gi = _pair_frames(pred.frame_names, gt, pred.source)
    _, sim = shape_metrics(pred.verts_cam[pi], pred.faces, gt.verts[gi], gt.faces)
    sims = frame_similarities(pred.verts_cam[pi], pred.faces, gt.verts[gi], gt.faces, sim)
    gt_of = dict(zip(pi.tolist(), gi.tolist()))
    sim_of = dict(zip(pi.tolist(), sims))
    roles = keypoint_roles(kps.names)
    pairs = [(p, q) for p, q in enumerate(counterparts(kps.names)) if q is not None]
    rows = []
    for s, fi, bary in render_frames(pred.verts_cam, pred.faces, pred.K, pred.image_size, 8, "cpu", False, None):
        for k in range(fi.shape[0]):
            t = s + k
            fn = pred.frame_names[t]
            if fn not in kps.frames or t not in gt_of:
                continue
            kp = kps.frames[fn]
            face, w, _ = surface_under_keypoints(fi[k], bary[k], kp[:, :2])
            for p, q in pairs:
                if kp[p, 2] <= 0 or face[p] < 0:
                    continue
                x = (w[p][:, None] * pred.verts_cam[t][pred.faces[face[p]]]).sum(0)
                g, o = gt.keypoints[kps.names[p]][gt_of[t]], gt.keypoints[kps.names[q]][gt_of[t]]
                rows.append((sim_of[t](x[None])[0], g, o, g[2] < o[2], roles[p].end))
    if not rows:
        return None
    P, G, O, N, E = (np.array(c) for c in zip(*rows))
    return keypoint_depths(P, G, O, N.astype(bool), E.astype(bool))


def phase_name(checkpoint: Path, steps_per_epoch: int) -> str:
    """``coarse``, ``warmup``, ``epoch N`` or ``done`` from a step checkpoint's name (``step-2-joint-000400.pt``)."""
    _, _, phase, step = checkpoint.stem.split("-")
    if phase == "warmup":
        return "coarse"
    if phase == "joint":
        k = int(step) // max(steps_per_epoch, 1)
        return "warmup" if k == 0 else f"epoch {k - 1}"
    return phase


def score_checkpoints(run: Path, seq: Path, device: torch.device) -> list[dict]:
    """Every step checkpoint of ``run`` scored as a finished fit (its rig through ``evaluate_run``), in order."""
    cfg = make_config(toml_path=run / "config.toml")
    spe = max(1, math.ceil(cfg.motion.steps / max(1, cfg.skeleton.epochs)))
    data = prepare_data(seq, cfg, run, device)
    with repeatable(cfg.repeatable and device.type == "cpu"):
        fitter = Fitter(data, coarse_model(data, cfg), cfg, run, device)
    out = []
    for ck in sorted((run / "checkpoints").glob("step-*.pt")):
        fitter.load_checkpoint(ck)
        with tempfile.TemporaryDirectory() as td:
            save_rig(Path(td), rig_from_model(fitter))
            m = evaluate_run(Path(td), None, masks=data.mask_dir, keypoints=data.keypoints_file,
                             ground_truth=data.ground_truth_dir, progress=False, framewise_limbs=False)
            depths = surface_depths(Path(td), seq)
        row = {"phase": phase_name(ck, spe), "checkpoint": ck.name, "bones": int(fitter.model.num_bones),
               "iou": m["mask_iou"]["mean"]}
        if "pck_t" in m:
            g = m["pck_t"]["groups"]
            row["pck_t"] = m["pck_t"]["pck"]
            row.update({f"pck_t_{k}": g[k]["pck"] for k in GROUPS})
            per = m["pck_t"]["per_keypoint"]
            row["worst"] = sorted(([k, v["pck"]] for k, v in per.items() if v["pck"] is not None), key=lambda r: r[1])[:3]
        if depths is not None:
            row["depths"] = depths
        log.info("%s %s: %s", run.name, row["phase"], {k: v for k, v in row.items() if k.startswith("pck_t")})
        out.append(row)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cases", nargs="+", default=["horse"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--preset", default="default")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--out-dir", default=str(REPO / "runs" / "bench"))
    ap.add_argument("--rescore", action="store_true", help="score the runs already in --out-dir, without fitting")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    device = resolve_device(args.device)
    work = Path(args.out_dir)
    dest = REPO / "benchmarks" / f"legs-{device.type}.json"
    header = dict(command=command_line(args.out_dir), device=str(device),
                  device_name=torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_name(),
                  cpu_count=os.cpu_count(), versions=versions(), git_commit=git_commit())
    for case in args.cases:
        seq = prepare_case(case, work)
        if seq is None:
            continue
        for seed in args.seeds:
            run = work / "runs" / f"{case}-s3o-{seed}"
            cfg = make_config(args.preset, overrides=args.overrides, seed=seed)
            if not args.rescore:
                spe = max(1, math.ceil(cfg.motion.steps / max(1, cfg.skeleton.epochs)))
                cfg = make_config(args.preset, overrides=args.overrides + [
                    f"output.checkpoint_every={spe}", f"output.keep_checkpoints={cfg.skeleton.epochs + 4}"], seed=seed)
                fit(seq, run, cfg, device)
            elif not (run / "checkpoints").is_dir():
                log.warning("%s: no checkpoints to score (fit it first, without --rescore)", run)
                continue
            entry = dict(case=case, seed=seed, preset=args.preset, overrides=args.overrides, method="s3o",
                         git_commit=header["git_commit"], phases=score_checkpoints(run, seq, device))
            record(dest, header, entry)
            print(f"wrote {dest}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
