#!/usr/bin/env python
"""Multi-video benchmark: videos of one object fitted together and each alone, in ``benchmarks/multi-<device>.json``.

    python scripts/bench_multi.py --device cpu [--cases robot4 horse2 horse-mirror] [--seeds 0 1 2]
                                  [--preset default] [--set key=value ...] [--out-dir DIR] [--no-alone] [--rescore]

Cases (:data:`CASES`), rendered from the glTF models of ../shared/data as ``scripts/bench_fit.py``'s are (48 frames
at 30 fps, 320x240, 15 degrees up; a case whose model is absent skips with a message):

* ``robot4``: three.js's RobotExpressive, Walking, seen at the same instants by 4 cameras standing still at
  azimuths 0, 90, 180 and 270 (its right flank, face, left flank, back), each turning to follow it (the ``pan`` path
  of :func:`s3o_warp.synth.camera.camera_path`); fitted with ``motion.synchronized=true``.
* ``horse2``: the Quaternius horse, Walk, by two orbits at different times: bench_fit's ``horse`` (azimuth -60 to 60,
  about its right flank) and one about its left flank (120 to 240).
* ``horse-mirror``: bench_fit's ``horse`` orbit and its mirror image (:func:`s3o_warp.synth.sequence.mirror_sequence`,
  masks and keypoints only): the fit is to register the mirrored video's orientation (the row's ``registration``)
  rather than average it in.

Each case's videos are rendered once into ``OUT_DIR/sequences/<case>/<video>/`` (reused by later runs), fitted
together into ``OUT_DIR/runs/<case>-<seed>/`` (``RUN/videos/<video>/`` holds each video's own run directory) and,
unless ``--no-alone``, each alone into ``OUT_DIR/runs/<case>-<video>-alone-<seed>/`` with the same settings and
``motion.synchronized=false``. A row per case and seed (:func:`multi_row`) holds, per video of the joint fit, the
figures of :data:`FIGURES` and the fit's registration of it (and, from the ground truth, how far off it is:
:func:`registration_errors`), their mean over the videos, the wall time, and the same
figures of each video fitted alone; it is recorded after the joint fit and again after each fit alone, merged into the
JSON file as bench_fit merges its rows (a rerun at the same commit replaces its row, other commits' rows stay).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh
from bench_fit import DATA, SYNTH, command_line, record
from scipy.spatial.transform import Rotation

from s3o_warp.config import make_config
from s3o_warp.evaluation.loaders import load_ground_truth
from s3o_warp.evaluation.report import evaluate_run
from s3o_warp.fit import fit, resolve_device
from s3o_warp.provenance import REPO, cpu_name, git_commit, versions
from s3o_warp.synth import make_sequence
from s3o_warp.synth.sequence import PROCEDURAL, mirror_sequence

_ROBOT = {k: v for k, v in SYNTH["robot"].items() if k != "azim"}
_HORSE = SYNTH["horse"]

CASES = {
    "robot4": dict(synchronized=True, videos={
        name: {**_ROBOT, "path": "pan", "azim": (a, a)}
        for name, a in (("right", 0.0), ("front", 90.0), ("left", 180.0), ("back", 270.0))}),
    "horse2": dict(synchronized=False, videos={"right": _HORSE, "left": {**_HORSE, "azim": (120.0, 240.0)}}),
    "horse-mirror": dict(synchronized=False, videos={"right": _HORSE, "mirrored": {"mirror": "right"}}),
}
"""Per case: whether its videos are the same instants (``motion.synchronized``) and its videos by name, each
:func:`s3o_warp.synth.make_sequence`'s arguments (``source`` under ../shared/data) or ``{"mirror": VIDEO}``, the
mirror image of an earlier video of the case."""

FIGURES = {
    "iou": ("mask_iou", "mean"),
    "pck_t": ("pck_t", "pck"),
    "fscore": ("shape_3d", "fscore"),
    "novel_iou_framewise": ("views", "framewise", "mean"),
    "novel_iou_sequence": ("views", "sequence", "mean"),
    "normal_consistency": ("surface", "normal_consistency"),
    "roughness": ("surface", "roughness", "pred"),
    "roughness_truth": ("surface", "roughness", "truth"),
    "pck_t_ends": ("pck_t", "groups", "ends", "pck"),
    "pck_t_rest": ("pck_t", "groups", "rest", "pck"),
    "pck_t_near": ("pck_t", "groups", "near", "pck"),
    "pck_t_far": ("pck_t", "groups", "far", "pck"),
    "limbs_distinct": ("skeleton", "limbs_distinct", "covered"),
    "limbs_total": ("skeleton", "limbs_distinct", "total"),
}
"""The figures a row keeps of a video's metrics, by where they stand in it: mask IoU, PCK-T (and by role: the limbs'
ends, the rest, the side facing the camera, the far side), F-score with the
sequence's alignment, novel-view IoU with each frame aligned and with the sequence's, normal consistency, roughness
(the truth's beside) and the limbs found with distinct joints of all. None where the metrics lack it (a mirrored
video has no ground truth: masks and keypoints only)."""


def prepare_videos(case: str, work: Path) -> dict[str, Path] | None:
    """The sequence folders of a case's videos by name (rendered on first use), or None when a model is missing."""
    if case not in CASES:
        raise SystemExit(f"bench_multi: unknown case {case}; choose from {', '.join(CASES)}")
    root = work / "sequences" / case
    todo = {name: spec for name, spec in CASES[case]["videos"].items() if not (root / name / "images").is_dir()}
    for spec in todo.values():  # every model first: a case is rendered whole or not at all
        if "source" in spec and spec["source"] not in PROCEDURAL and not (DATA / spec["source"]).is_file():
            print(f"bench_multi: skip {case}: {DATA / spec['source']} not found (set S3O_SHARED_DATA)", file=sys.stderr)
            return None
    videos = {}
    for name, spec in CASES[case]["videos"].items():
        seq = videos[name] = root / name
        if name not in todo:
            continue
        if "mirror" in spec:
            mirror_sequence(videos[spec["mirror"]], seq)
        else:
            spec = dict(spec)
            src = spec.pop("source")
            make_sequence(seq, source=src if src in PROCEDURAL else DATA / src, **spec)
    return videos


def video_figures(metrics: dict) -> dict:
    """The :data:`FIGURES` of one video's metrics dict (a one-video fit's, or one of ``fit(...)["videos"]``)."""
    out = {}
    for name, keys in FIGURES.items():
        v = metrics
        for k in keys:
            v = v.get(k) if isinstance(v, dict) else None
        out[name] = v
    return out


def mean_figures(videos: dict[str, dict]) -> dict:
    """Each of :data:`FIGURES` averaged over the videos that have it (None where none has)."""
    out = {}
    for name in FIGURES:
        vals = [f[name] for f in videos.values() if f.get(name) is not None]
        out[name] = sum(vals) / len(vals) if vals else None
    return out


def multi_row(joint: dict, wall: float, alone: dict[str, tuple[dict, float]] | None = None, **keys) -> dict:
    """A benchmark row: ``keys`` (case, seed, settings...), then per video of the joint fit's result ``joint``
    (``{"videos": {name: metrics}, "registration": {name: {...}}, ...}``) its figures and registration (the
    registration's numbers and words; lists left out), their mean over the videos (:func:`mean_figures`), the wall
    time, and, from ``alone`` (each video's own fit: its metrics and wall time), the same figures, their mean and
    the total wall time."""
    reg = joint.get("registration") or {}
    videos = {name: {**video_figures(m), "registration": {k: v for k, v in (reg.get(name) or {}).items()
                                                          if v is None or isinstance(v, (bool, int, float, str))}}
              for name, m in joint["videos"].items()}
    row = {**keys, "videos": list(videos), "wall_seconds": round(wall, 1), "joint": videos,
           "mean": mean_figures(videos)}
    if alone:
        row["alone"] = {name: {**video_figures(m), "wall_seconds": round(w, 1)} for name, (m, w) in alone.items()}
        row["alone_mean"] = mean_figures(row["alone"])
        row["alone_wall_seconds"] = round(sum(w for _, w in alone.values()), 1)
    return row


def registration_errors(run: Path, videos: dict[str, Path], frames: int = 8) -> dict[str, float]:
    """Per video with ground truth, how far (degrees) the joint fit's registration of it is from the first such
    video's, as the truth sees both. On ``frames`` frames spread over each video, the fitted body's rotation in the
    video's camera (Procrustes from the shared ``canonical.ply`` to the frame's fitted vertices, no alignment) is
    taken back through the true camera (``cam_from_world``: world = the model's own frame): the canonical body's
    orientation in the model's frame that this video implies. The angle between one video's mean and the first's is
    the error: 0 when every video sees the canonical body turned as the truth is, ~180 for a video registered the
    wrong way round. The bodies' own turns in their world (none in the benchmark's clips) count as error."""
    if not (run / "canonical.ply").is_file():
        return {}
    X = np.asarray(trimesh.load(run / "canonical.ply", process=False).vertices, np.float64)
    X = X - X.mean(0)
    turns = {}
    for name, seq in videos.items():
        own = run / "videos" / name / "motion.npz"
        if not (seq / "ground_truth").is_dir() or not own.is_file():
            continue
        gt = load_ground_truth(seq / "ground_truth")
        V = np.load(own)["verts_cam"].astype(np.float64)
        if gt.cam_from_world is None or V.shape[1] != len(X) or V.shape[0] != gt.cam_from_world.shape[0]:
            continue
        rots = []
        for f in np.linspace(0, len(V) - 1, frames).round().astype(int):
            in_cam = Rotation.align_vectors(V[f] - V[f].mean(0), X)[0]  # canonical -> this video's camera
            rots.append(Rotation.from_matrix(gt.cam_from_world[f, :3, :3]).inv() * in_cam)  # -> the model's frame
        turns[name] = Rotation.concatenate(rots).mean()
    if not turns:
        return {}
    ref = turns[next(iter(turns))]
    return {name: round(float(np.degrees((q * ref.inv()).magnitude())), 1) for name, q in turns.items()}


def rescore_row(dest: Path, work: Path, case: str, seed: int, preset: str, overrides: list[str],
                videos: dict[str, Path]) -> dict | None:
    """The newest row of ``case`` and ``seed`` (same preset and overrides) in ``dest`` whose joint fit is the one in
    ``work`` (the same mask IoU per video as its ``metrics.json``), its runs scored again with
    this commit's metrics (:func:`s3o_warp.evaluation.report.evaluate_run` on each video's run directory and each
    fit alone); its fits' commit and wall times kept, ``rescored_commit`` added. None when there is no such row."""
    run = work / "runs" / f"{case}-{seed}"
    if not (run / "metrics.json").is_file():
        return None
    top = json.loads((run / "metrics.json").read_text())
    ious = {name: (m.get("mask_iou") or {}).get("mean") for name, m in (top.get("videos") or {}).items()}
    rows = json.loads(dest.read_text())["results"] if dest.is_file() else []
    rows = [r for r in rows if (r.get("case"), r.get("seed"), r.get("preset"), r.get("overrides")) ==
            (case, seed, preset, overrides)  # and the row of these runs: its mask IoU is their metrics.json's
            and {name: v.get("iou") for name, v in r["joint"].items()} == ious]
    if not rows:
        return None
    old = rows[-1]
    joint = {"videos": {name: evaluate_run(run / "videos" / name, seq, progress=False) for name, seq in videos.items()},
             "registration": top.get("registration") or {}}
    alone = {name: (evaluate_run(work / "runs" / f"{case}-{name}-alone-{seed}", seq, progress=False),
                    old["alone"][name]["wall_seconds"])
             for name, seq in videos.items() if name in (old.get("alone") or {})}
    keys = {k: old[k] for k in ("command", "case", "seed", "preset", "overrides", "synchronized", "mirror_of",
                                "git_commit", "device_name") if k in old}
    keys.update(rescored_commit=git_commit(), registration_error_deg=registration_errors(run, videos))
    return multi_row(joint, old["wall_seconds"], alone or None, **keys)


def _timed_fit(seq, run: Path, cfg, device) -> tuple[dict, float]:
    t0 = time.perf_counter()
    metrics = fit(seq, run, cfg, device)
    return metrics, time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--preset", default="default")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--out-dir", default=str(REPO / "runs" / "bench"))
    ap.add_argument("--alone", action=argparse.BooleanOptionalAction, default=True,
                    help="also fit each video alone with the same settings (motion.synchronized=false); default on")
    ap.add_argument("--rescore", action="store_true",
                    help="score the runs already in OUT_DIR again with this commit's metrics, without fitting; each "
                         "row keeps its fits' commit and wall times and gains rescored_commit")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")  # the fits' logs to stderr
    device, work = resolve_device(args.device), Path(args.out_dir)
    dest = REPO / "benchmarks" / f"multi-{device.type}.json"
    header = {"command": command_line(args.out_dir), "device": str(device),
              "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_name(),
              "cpu_count": os.cpu_count(), "versions": versions(), "git_commit": git_commit()}
    for case in args.cases:
        videos = prepare_videos(case, work)
        if videos is None:
            continue
        mirrors = {name: spec["mirror"] for name, spec in CASES[case]["videos"].items() if "mirror" in spec}
        sync = "true" if CASES[case]["synchronized"] else "false"
        for seed in args.seeds:
            if args.rescore:
                row = rescore_row(dest, work, case, seed, args.preset, args.overrides, videos)
                if row is None:
                    print(f"bench_multi: no row of {case} seed {seed} to rescore in {dest}", file=sys.stderr)
                    continue
                record(dest, header, row)
                print(json.dumps(row, default=float), flush=True)
                continue
            cfg = make_config(args.preset, overrides=[f"motion.synchronized={sync}"] + args.overrides, seed=seed)
            keys = dict(command=header["command"], case=case, seed=seed, preset=args.preset, overrides=args.overrides,
                        synchronized=cfg.motion.synchronized, **({"mirror_of": mirrors} if mirrors else {}),
                        git_commit=header["git_commit"], device_name=header["device_name"])
            joint, wall = _timed_fit(list(videos.values()), work / "runs" / f"{case}-{seed}", cfg, device)
            keys["registration_error_deg"] = registration_errors(work / "runs" / f"{case}-{seed}", videos)
            row = multi_row(joint, wall, **keys)
            record(dest, header, row)
            if args.alone:
                solo = make_config(args.preset, overrides=args.overrides + ["motion.synchronized=false"], seed=seed)
                alone: dict[str, tuple[dict, float]] = {}
                for name, seq in videos.items():
                    alone[name] = _timed_fit(seq, work / "runs" / f"{case}-{name}-alone-{seed}", solo, device)
                    row = multi_row(joint, wall, alone, **keys)
                    record(dest, header, row)
            print(json.dumps(row, default=float), flush=True)
    print(f"wrote {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
