#!/usr/bin/env python
"""Fit benchmark: accuracy and wall time of whole fits, written to ``benchmarks/fit-<device>.json``.

    python scripts/bench_fit.py --device cpu --cases quadruped [fox horse robot robot-dance lizard cows dog dance-twirl] [--methods s3o virtual]
                                [--seeds 0 1 2] [--preset default] [--set key=value ...] [--out-dir DIR] [--profile]

Cases: ``quadruped`` (the built-in default shot, the README's main command), ``fox`` (Khronos Fox Walk,
48 frames, 320x240, 90-degree orbit), ``fox120`` (the same clip with a 120-degree orbit), ``horse`` (Quaternius Horse Walk, 48 frames, 320x240, 120-degree
orbit), ``deer`` (Quaternius Deer Walk) and ``husky`` (Quaternius Husky Gallop, looped), both rendered as the horse is,
``robot`` (three.js's RobotExpressive biped, Walking, 48 frames, 320x240, 120-degree orbit), ``robot-dance``
(the same robot's Dance seen from the front: a 60-degree orbit about its front, arms away from the body), ``lizard``
(the built-in lizard's crawl, 48 frames, 320x240, 120-degree orbit from 30 degrees up), ``cows`` / ``dog``
(DAVIS with BADJA keypoints), ``dance-twirl`` (DAVIS, a dancer; no keypoints, so no PCK-T), ``cows-box`` /
``dog-box`` (cows and dog on masks made from a box on frame 0, :data:`BOXED`). Cases that need ../shared/data skip with a
message when it is absent. Each fit's metrics, per-phase wall time (from log.jsonl) and total time
are recorded with the command, device, versions and git commit. Results are merged into the JSON file
(one entry per case/method/seed/preset/overrides and commit; a rerun at the same commit replaces its
entry, other commits' entries stay as history), so cases can be run in separate invocations, side by side too.

``--profile`` writes ``benchmarks/profile-<device>.json`` instead: the same rows with, per phase of the fit, its
wall time, steps and a step's split into Warp kernels, torch ops, host syncs and Python
(:mod:`s3o_warp.run.profile`); each fit starts from an empty run directory, so the optical flow is computed.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import logging
import os
import shutil
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from s3o_warp.config import make_config
from s3o_warp.data.crops import mask_bbox
from s3o_warp.data.io import copy_file, write_image, write_text
from s3o_warp.data.keypoints import badja_to_keypoints, write_keypoints
from s3o_warp.evaluation.report import evaluate_run
from s3o_warp.fit import fit, resolve_device
from s3o_warp.masks.make import make_masks
from s3o_warp.provenance import REPO, cpu_name, git_commit, versions
from s3o_warp.run.profile import FitProfile
from s3o_warp.synth import make_sequence
from s3o_warp.synth.sequence import PROCEDURAL

DATA = Path(os.environ.get("S3O_SHARED_DATA", REPO.parent / "shared" / "data"))

SYNTH = {
    "quadruped": dict(source="quadruped"),
    "fox": dict(source="gltf/khronos_Fox.glb", clip="Walk", frames=48, fps=30.0, size=(320, 240), azim=(-45.0, 45.0), elev=15.0),
    "fox120": dict(source="gltf/khronos_Fox.glb", clip="Walk", frames=48, fps=30.0, size=(320, 240), azim=(-60.0, 60.0), elev=15.0),
    "horse": dict(source="gltf/quaternius_Horse.glb", clip="Walk", frames=48, fps=30.0, size=(320, 240), azim=(-60.0, 60.0), elev=15.0),
    "deer": dict(source="gltf/quaternius_Deer.glb", clip="Walk", frames=48, fps=30.0, size=(320, 240), azim=(-60.0, 60.0), elev=15.0),
    "husky": dict(source="gltf/quaternius_Husky.glb", clip="Gallop", frames=48, fps=30.0, size=(320, 240), azim=(-60.0, 60.0),
                  elev=15.0),
    "robot": dict(source="gltf/threejs_RobotExpressive.glb", clip="Walking", frames=48, fps=30.0, size=(320, 240),
                  azim=(-60.0, 60.0), elev=15.0),
    "robot-dance": dict(source="gltf/threejs_RobotExpressive.glb", clip="Dance", frames=48, fps=30.0, size=(320, 240),
                        azim=(60.0, 120.0), elev=15.0),
    "lizard": dict(source="lizard", frames=48, fps=30.0, size=(320, 240), azim=(-60.0, 60.0), elev=30.0),
}
DAVIS = {"cows": "cows", "dog": "dog", "dance-twirl": "dance-twirl"}
BOXED = {"cows-box": "cows", "dog-box": "dog"}
"""Cases fitted on masks made from one box (``s3o_warp.masks``, the default segmenter) instead of the true ones;
their IoU and PCK-T are scored against the true masks (``iou_own_masks``: against the masks fitted)."""

BOX_MARGIN = 4
"""Pixels between the true mask's bounding box and a benchmark's box (a hand-drawn box leaves some room)."""


def true_box(mask: np.ndarray) -> tuple[int, int, int, int]:
    """The box a benchmark draws around a true mask: its bounding box grown by :data:`BOX_MARGIN`, inside the frame."""
    H, W = mask.shape
    x0, y0, x1, y1 = mask_bbox(mask)
    return (max(0, x0 - BOX_MARGIN), max(0, y0 - BOX_MARGIN), min(W - 1, x1 + BOX_MARGIN), min(H - 1, y1 + BOX_MARGIN))


def command_line(out_dir) -> str:
    """This process's command as a benchmark row records it: the output folder as ``OUT_DIR`` (a machine's own path
    says nothing to another)."""
    return " ".join(["python"] + ["OUT_DIR" if a == str(out_dir) else a for a in sys.argv])


def prepare_case(case: str, work: Path) -> Path | None:
    """The sequence folder of a case (rendered or converted on first use), or None when data is missing."""
    seq = work / "sequences" / case
    if case in SYNTH:
        spec = dict(SYNTH[case])
        src = spec.pop("source")
        if src not in PROCEDURAL:
            src = DATA / src
            if not src.is_file() and not (seq / "images").is_dir():  # a sequence rendered earlier needs no source
                print(f"bench_fit: skip {case}: {src} not found (set S3O_SHARED_DATA)", file=sys.stderr)
                return None
        if not (seq / "images").is_dir():
            make_sequence(seq, source=src, **spec)
        return seq
    if case in DAVIS:
        name = DAVIS[case]
        img = DATA / "davis" / "JPEGImages" / "480p" / name
        if not img.is_dir():
            print(f"bench_fit: skip {case}: {img} not found", file=sys.stderr)
            return None
        seq.mkdir(parents=True, exist_ok=True)
        for sub, src in (("images", img), ("masks", DATA / "davis" / "Annotations" / "480p" / name)):
            if not (seq / sub).exists():
                os.symlink(src, seq / sub) if hasattr(os, "symlink") else shutil.copytree(src, seq / sub)
        badja = DATA / "badja" / f"{name}.json"
        if badja.is_file() and not (seq / "keypoints.json").is_file():  # a sequence without one has no PCK-T
            write_keypoints(badja_to_keypoints(badja, frame_size=(480, 854)), seq / "keypoints.json")
        return seq
    if case in BOXED:
        truth = prepare_case(BOXED[case], work)
        if truth is None:
            return None
        if not (seq / "masks.json").is_file():
            first = cv2.imread(str(sorted((truth / "masks").iterdir())[0]), cv2.IMREAD_GRAYSCALE) > 127
            make_masks(truth / "images", seq, {0: true_box(first)})
            copy_file(truth / "keypoints.json", seq / "keypoints.json")
        return seq
    raise SystemExit(f"bench_fit: unknown case {case}; choose from {', '.join(list(SYNTH) + list(DAVIS) + list(BOXED))}")


def resamplings(run: Path) -> list[str]:
    """Each even resampling of the fit: ``BEFORE->AFTER`` vertices and the method used, or ``refused``."""
    recs = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if line.strip()]
    return [f"{r['vertices_before']}->{r['vertices_after']} " + ("refused" if r["kept"] else r.get("method") or "used")
            for r in recs if r.get("what") == "resample"]


def phase_times(run: Path) -> dict:
    recs = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if line.strip()]
    recs = [r for r in recs if r["phase"] != "eval"]
    out, prev = {}, 0.0
    for phase in dict.fromkeys(r["phase"] for r in recs):
        last = [r for r in recs if r["phase"] == phase][-1]["seconds"]
        out[phase] = round(last - prev, 2)
        prev = last
    return out


def figure_path(case: str, device: str, tag: str = "") -> Path:
    """The repository's t_o figure of a sequence: ``renders/skeleton_t_o-CASE[-TAG]-DEVICE.png``."""
    return REPO / "renders" / (f"skeleton_t_o-{case}" + (f"-{tag}" if tag else "") + f"-{device}.png")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cases", nargs="+", default=["quadruped"])
    ap.add_argument("--methods", nargs="+", default=["s3o"], help="skeleton.method values: s3o, virtual, fixed")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--preset", default="default")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--out-dir", default=str(REPO / "runs" / "bench"))
    ap.add_argument("--t-o", nargs="+", type=float, default=None,
                    help="skeleton granularity study: fit once per merge threshold t_o (e.g. 0.99 0.95 0.90; the later ones branched "
                         "from the first's state before its first merge, see --no-branch) and put the "
                         "three dominant-bone pictures side by side in renders/skeleton_t_o-CASE-DEVICE.png of the "
                         "repository (and renders/skeleton_t_o.png of the last run)")
    ap.add_argument("--no-branch", action="store_true",
                    help="with --t-o: a whole fit per t_o (default: the first t_o's fit, the others branched from its state "
                         "just before the first merge, fit(..., branch_from=...), which gives the same result)")
    ap.add_argument("--branch-from", default=None, metavar="RUN_TEMPLATE",
                    help="start each fit from another run's state just before its first merge (fit(..., branch_from=...)); "
                         "{case} and {seed} are filled in, e.g. runs/bench/runs/{case}-s3o-{seed}. Only the settings the "
                         "refinement reads (skeleton.t_o, t_u, t_d) may differ from that run's")
    ap.add_argument("--figure-tag", default="",
                    help="with --t-o: name the repository's figure renders/skeleton_t_o-CASE-TAG-DEVICE.png, so a study "
                         "with other settings (e.g. --set skeleton.t_d=0.25 --figure-tag td25) does not "
                         "overwrite the sequence's figure")
    ap.add_argument("--profile", action="store_true",
                    help="write benchmarks/profile-<device>.json: per phase, wall time, steps and a step's split into "
                         "kernels, torch ops, syncs and Python (no fit-<device>.json row: profiling slows the fit)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")  # the fit's log (M-step edits) to stderr
    device = resolve_device(args.device)
    work = Path(args.out_dir)
    dest = REPO / "benchmarks" / f"{'profile' if args.profile else 'fit'}-{device.type}.json"
    header = dict(
        command=command_line(args.out_dir),
        device=str(device),
        device_name=torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_name(),
        cpu_count=os.cpu_count(),
        versions=versions(),
        git_commit=git_commit(),
    )
    for case in args.cases:
        seq = prepare_case(case, work)
        if seq is None:
            continue
        variants = [(m, None) for m in args.methods] if not args.t_o else [("s3o", t) for t in args.t_o]
        pictures, trunk = [], {}
        for method, t_o in variants:
            for seed in args.seeds:
                extra = [f"skeleton.t_o={t_o}"] if t_o is not None else []
                cfg = make_config(args.preset, overrides=[f"skeleton.method={method}"] + extra + args.overrides, seed=seed)
                run = work / "runs" / (f"{case}-{method}-{seed}" + (f"-t_o{t_o}" if t_o is not None else ""))
                parent = trunk.get(seed) if t_o is not None and not args.no_branch else None
                if parent is None and args.branch_from:
                    parent = Path(args.branch_from.format(case=case, seed=seed))
                if args.profile:  # from nothing: the optical flow is computed, not read from the cache
                    run = run.with_name(run.name + "-profile")
                    shutil.rmtree(run, ignore_errors=True)
                t0 = time.perf_counter()
                with FitProfile(device) if args.profile else contextlib.nullcontext() as prof:
                    metrics = fit(seq, run, cfg, device, branch_from=parent)
                wall = time.perf_counter() - t0
                if t_o is not None and parent is None and (run / "checkpoints" / "branch.pt").is_file():
                    trunk[seed] = run
                if t_o is not None:
                    pictures.append((t_o, run / "renders" / "bones.png"))
                entry = {
                    "command": header["command"],
                    "case": case, "method": method, "seed": seed, "preset": args.preset, "overrides": args.overrides + extra,
                    "wall_seconds": round(wall, 1), "phase_seconds": phase_times(run),
                    **({"branched_from": str(parent) if args.branch_from else parent.name, "note": "wall_seconds: this fit's own (after the branch); "
                        "phase_seconds: the shared part's from the parent's log"} if parent is not None else {}),
                    "iou": (metrics.get("mask_iou") or {}).get("mean"),
                    "pck_t": (metrics.get("pck_t") or {}).get("pck"),
                    "chamfer": (metrics.get("shape_3d") or {}).get("chamfer"),
                    "fscore": (metrics.get("shape_3d") or {}).get("fscore"),
                    **views_figures(metrics),
                    **keypoint_figures(metrics),
                    "skeleton": {k: v for k, v in (metrics.get("skeleton") or {}).items() if k != "per_frame"},
                    "bones": len(json.loads((run / "skeleton.json").read_text())["bones"]),
                    "resamplings": resamplings(run),
                    "git_commit": header["git_commit"],  # the code this process loaded, not HEAD when the fit ends
                    "device_name": header["device_name"],
                    **({"profile": prof.report()} if prof is not None else {}),
                }
                if case in BOXED:  # scored against the true masks (and their areas for PCK-T)
                    true = evaluate_run(run, prepare_case(BOXED[case], work), progress=False)
                    entry.update(iou_own_masks=entry["iou"], iou=true["mask_iou"]["mean"], pck_t=true["pck_t"]["pck"],
                                 **keypoint_figures(true))
                print(json.dumps(entry), flush=True)
                record(dest, header, entry)
        if pictures:  # the run's own copy, and the repository's figure for this sequence
            _compose(pictures, run / "renders" / "skeleton_t_o.png")
            _compose(pictures, figure_path(case, device.type, args.figure_tag))
    print(f"wrote {dest}")
    return 0


def views_figures(metrics: dict) -> dict:
    """The figures from every side of a fit's metrics (synthetic cases): novel-view IoU per alignment and view,
    F-score at 1 % and 2 % with each frame aligned, normal consistency and roughness (the truth's beside), the
    width ratio and the root's turn error in degrees (mean, max and last frame of each frame's own alignment
    against the sequence's; about the vertical, signed: the last frame's turn and its change from the first's)."""
    if "views" not in metrics:
        return {}
    v, s = metrics["views"], metrics["surface"]
    return {"novel_iou": {k: {"mean": v[k]["mean"], **v[k]["per_view"]} for k in ("sequence", "framewise")},
            "fscore_framewise": s["fscore"], "normal_consistency": s["normal_consistency"],
            "roughness": {k: s["roughness"][k] for k in ("pred", "truth")},
            **({"width_ratio": {k: v["width_ratio"][k] for k in ("pred", "truth")}} if "width_ratio" in v else {}),
            **({"turn_error": {k: v["turn_error"].get(k) for k in TURN_FIGURES}} if "turn_error" in v else {})}


def keypoint_figures(metrics: dict) -> dict:
    """PCK-T by role (``pck_t.groups``: the limbs' ends, the rest, the side facing the camera and the far side, the
    worst keypoint) and how often a fitted limb follows another true limb (``limb_identity.mean_swapped``)."""
    g = (metrics.get("pck_t") or {}).get("groups") or {}
    out = {f"pck_t_{k}": (g.get(k) or {}).get("pck") for k in ("ends", "rest", "near", "far")} if g else {}
    if g.get("worst"):
        out["pck_t_worst"] = g["worst"]
    if "limb_identity" in metrics:
        out["swapped"] = metrics["limb_identity"].get("mean_swapped")
    return out


TURN_FIGURES = ("mean_deg", "max_deg", "end_deg", "end_vertical_deg", "drift_vertical_deg")
"""The turn error's figures a row keeps (metrics.json's ``views.turn_error`` has each frame's too)."""


def _same_run(a: dict, b: dict) -> bool:
    """A rerun of one fit: the same case, method, seed, preset, overrides and commit (other commits' rows are kept)."""
    return all(a.get(k) == b.get(k) for k in ("case", "method", "seed", "preset", "overrides", "git_commit"))


def record(dest: Path, header: dict, entry: dict) -> None:
    """Merge one fit's entry into ``dest`` (replacing an earlier entry of the same fit, :func:`_same_run`),
    re-reading the file under a lock so fits run side by side do not drop each other's rows;
    written atomically."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    with open(dest.with_suffix(".json.lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        doc = json.loads(dest.read_text()) if dest.is_file() else {"results": []}
        doc.update(header)
        doc["results"] = [r for r in doc["results"] if not _same_run(r, entry)] + [entry]
        write_text(dest, json.dumps(doc, indent=2, default=float))


def _compose(pictures, dest: Path) -> None:
    """Side by side dominant-bone pictures labelled with their t_o."""
    imgs = []
    for t_o, p in pictures:
        im = cv2.imread(str(p))
        if im is None:
            continue
        cv2.putText(im, f"t_o = {t_o:.2f}", (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
        imgs.append(im)
    if imgs:
        dest.parent.mkdir(parents=True, exist_ok=True)
        write_image(dest, np.concatenate(imgs, 1)[..., ::-1])  # BGR as read -> RGB
        print(f"wrote {dest}")


if __name__ == "__main__":
    sys.exit(main())
