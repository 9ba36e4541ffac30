#!/usr/bin/env python
"""Masks from one box: mask IoU against the true masks, the frames flagged, the figure after one ``--box-at`` and
time per frame, written to ``benchmarks/masks-cpu.json``.

    python scripts/bench_masks.py [--cases CASE ...] [--frame K] [--out-dir DIR]

Each case's frames go through ``s3o_warp.masks.make_masks`` (the default segmenter) with one box on frame K (default
0): the true mask's bounding box grown by a few pixels (``bench_fit.true_box``), as a user would draw it. Then, where
frames were flagged (or the object was lost), as a user told by the warning would: once more with a second box, on
the first frame flagged (or lost), drawn the same way. Cases: every DAVIS 480p clip under the shared data (the
default: all of them, then ``fox120`` and ``horse``, the synthetic renders of ``scripts/bench_fit.py``). Cases whose
data is missing skip with a message. A rerun at the same commit replaces its entry.

Per case: the mean and worst IoU; the frames flagged; ``missed``, the frames under IoU 0.70 that are not flagged;
``jumps_unflagged``, the frames whose mask area changes by more than 1.5x from the previous frame's and that are
not flagged; and the same figures after the second box (``box_at``).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from s3o_warp.data.io import write_text
from s3o_warp.errors import InputError
from s3o_warp.masks.make import make_masks
from s3o_warp.provenance import REPO, cpu_name, git_commit, versions

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_fit import DATA, SYNTH, command_line, prepare_case, true_box  # noqa: E402

DAVIS_FRAMES = DATA / "davis" / "JPEGImages" / "480p"

MISSED_BELOW = 0.70
"""A frame under this IoU should be flagged."""

JUMP = 1.5
"""A mask whose area changes by more than this factor from the previous frame's should be flagged."""


def davis_cases() -> list[str]:
    return sorted(p.name for p in DAVIS_FRAMES.iterdir() if p.is_dir()) if DAVIS_FRAMES.is_dir() else []


def frames_and_truth(case: str, work: Path) -> tuple[Path, Path] | None:
    if case in SYNTH:
        seq = prepare_case(case, work)
        return None if seq is None else (seq / "images", seq / "masks")
    img = DAVIS_FRAMES / case
    if not img.is_dir():
        print(f"bench_masks: skip {case}: {img} not found (set S3O_SHARED_DATA)", file=sys.stderr)
        return None
    return img, DATA / "davis" / "Annotations" / "480p" / case


def measure(images: Path, out: Path, boxes: dict, truth: list[np.ndarray]) -> dict:
    """One ``make_masks`` run scored against ``truth``."""
    t0 = time.perf_counter()
    try:
        make_masks(images, out, boxes)
    except InputError as e:  # the object lost: the frame the message names
        lost = re.search(r"lost at frame (\d+)", str(e))
        return dict(lost_at=int(lost.group(1)) if lost else None, error=str(e),
                    seconds=round(time.perf_counter() - t0, 1))
    seconds = time.perf_counter() - t0
    rec = json.loads((out / "masks.json").read_text())
    made = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 127 for p in sorted((out / "masks").iterdir())]
    iou = np.array([(a & b).sum() / max((a | b).sum(), 1) for a, b in zip(made, truth)])
    area = np.array([m.sum() for m in made], np.float64)
    flagged = set(rec["flagged"])
    ratio = np.maximum(area[1:], 1) / np.maximum(area[:-1], 1)
    jumps = [int(k) + 1 for k in np.flatnonzero((ratio > JUMP) | (ratio < 1 / JUMP))]
    return dict(
        iou_mean=round(float(iou.mean()), 4), iou_min=round(float(iou.min()), 4), worst_frame=int(iou.argmin()),
        flagged=rec["flagged"], hidden=rec["hidden"],
        missed=[int(k) for k in np.flatnonzero(iou < MISSED_BELOW) if k not in flagged],
        jumps_unflagged=[k for k in jumps if k not in flagged],
        seconds=round(seconds, 1), seconds_per_frame=round(seconds / len(made), 3),
        iou_per_frame=[round(float(v), 4) for v in iou], confidence=rec["confidence"],
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=None, help="default: every DAVIS clip found, fox120, horse")
    ap.add_argument("--frame", type=int, default=0, help="the frame the box is drawn on")
    ap.add_argument("--out-dir", default=str(REPO / "runs" / "bench"))
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR, format="%(name)s: %(message)s")
    work = Path(args.out_dir)
    dest = REPO / "benchmarks" / "masks-cpu.json"
    header = dict(
        command=command_line(args.out_dir),
        device="cpu", device_name=cpu_name(), cpu_count=os.cpu_count(), versions=versions(),
        opencv=cv2.__version__, git_commit=git_commit(),
    )
    for case in args.cases or davis_cases() + ["fox120", "horse"]:
        paths = frames_and_truth(case, work)
        if paths is None:
            continue
        images, truth_dir = paths
        truth = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 127 for p in sorted(truth_dir.iterdir())]
        H, W = truth[args.frame].shape
        box = true_box(truth[args.frame])
        one = measure(images, work / "masks" / case, {args.frame: box}, truth)
        entry = dict(header, case=case, frames=len(truth), size=[W, H], frame=args.frame, box=list(box), **one,
                     torch_threads=torch.get_num_threads())
        second = one["flagged"][0] if one.get("flagged") else one.get("lost_at")
        if second is not None and second != args.frame:
            boxes = {args.frame: box, second: true_box(truth[second])}
            two = measure(images, work / "masks" / f"{case}-box-at", boxes, truth)
            entry["box_at"] = dict(frame=second, box=list(boxes[second]),
                                   **{k: v for k, v in two.items() if k not in ("iou_per_frame", "confidence")})
        print(json.dumps({k: v for k, v in entry.items() if k not in ("iou_per_frame", "confidence", "command",
                                                                       "versions")}), flush=True)
        doc = json.loads(dest.read_text()) if dest.is_file() else {"results": []}
        doc["results"] = [r for r in doc["results"] if not (r["case"] == case and r["frame"] == args.frame
                                                            and r["git_commit"] == entry["git_commit"])] + [entry]
        write_text(dest, json.dumps(doc, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
