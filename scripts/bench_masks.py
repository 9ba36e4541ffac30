#!/usr/bin/env python
"""Masks from one box: mask IoU against the true masks and time per frame, written to ``benchmarks/masks-cpu.json``.

    python scripts/bench_masks.py [--cases cows dog fox120 horse] [--frame K] [--out-dir DIR]

Each case's frames go through ``s3o_warp.masks.make_masks`` (the default segmenter) with one box on frame K (default
0): the true mask's bounding box grown by a few pixels (``bench_fit.true_box``), as a user would draw it. Cases: ``cows`` and
``dog`` (DAVIS 480p), ``fox120`` and ``horse`` (the synthetic renders of ``scripts/bench_fit.py``). Cases whose data
is missing skip with a message. A rerun at the same commit replaces its entry.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from s3o_warp.data.io import write_text
from s3o_warp.masks.make import make_masks
from s3o_warp.provenance import REPO, cpu_name, git_commit, versions

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_fit import DATA, SYNTH, command_line, prepare_case, true_box  # noqa: E402


def frames_and_truth(case: str, work: Path) -> tuple[Path, Path] | None:
    if case in SYNTH:
        seq = prepare_case(case, work)
        return None if seq is None else (seq / "images", seq / "masks")
    img = DATA / "davis" / "JPEGImages" / "480p" / case
    if not img.is_dir():
        print(f"bench_masks: skip {case}: {img} not found (set S3O_SHARED_DATA)", file=sys.stderr)
        return None
    return img, DATA / "davis" / "Annotations" / "480p" / case


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["cows", "dog", "fox120", "horse"])
    ap.add_argument("--frame", type=int, default=0, help="the frame the box is drawn on")
    ap.add_argument("--out-dir", default=str(REPO / "runs" / "bench"))
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    work = Path(args.out_dir)
    dest = REPO / "benchmarks" / "masks-cpu.json"
    header = dict(
        command=command_line(args.out_dir),
        device="cpu", device_name=cpu_name(), cpu_count=os.cpu_count(), versions=versions(),
        opencv=cv2.__version__, git_commit=git_commit(),
    )
    for case in args.cases:
        paths = frames_and_truth(case, work)
        if paths is None:
            continue
        images, truth_dir = paths
        truth = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 127 for p in sorted(truth_dir.iterdir())]
        H, W = truth[args.frame].shape
        box = true_box(truth[args.frame])
        out = work / "masks" / case
        t0 = time.perf_counter()
        make_masks(images, out, {args.frame: box})
        seconds = time.perf_counter() - t0
        made = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 127 for p in sorted((out / "masks").iterdir())]
        iou = np.array([(a & b).sum() / max((a | b).sum(), 1) for a, b in zip(made, truth)])
        entry = dict(header, case=case, frames=len(made), size=[W, H], frame=args.frame, box=list(box),
                     iou_mean=round(float(iou.mean()), 4), iou_min=round(float(iou.min()), 4),
                     worst_frame=int(iou.argmin()), iou_per_frame=[round(float(v), 4) for v in iou],
                     seconds=round(seconds, 1), seconds_per_frame=round(seconds / len(made), 3),
                     torch_threads=torch.get_num_threads())
        print(json.dumps({k: v for k, v in entry.items() if k != "iou_per_frame"}), flush=True)
        doc = json.loads(dest.read_text()) if dest.is_file() else {"results": []}
        doc["results"] = [r for r in doc["results"] if not (r["case"] == case and r["frame"] == args.frame
                                                            and r["git_commit"] == entry["git_commit"])] + [entry]
        write_text(dest, json.dumps(doc, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
