#!/usr/bin/env python
"""Controls of the figures from every side: the ground truth scored against itself (the top of every scale) and the
ground truth frozen in its first pose (clearly lower), on the synthetic cases of ``scripts/bench_fit.py``; written to
``benchmarks/views-controls.json``.

    python scripts/bench_views.py [--cases quadruped fox fox120 horse] [--out-dir DIR]

Each control is an ordinary ``motion.npz`` scored by ``evaluate_run``, so the whole path a fit's scores take is the
one measured: novel-view IoU with the sequence's alignment and with each frame's own, F-score at 1 % and 2 %,
normal consistency and roughness.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from bench_fit import SYNTH, prepare_case, views_figures

from s3o_warp.data.io import write_text
from s3o_warp.evaluation.loaders import load_ground_truth
from s3o_warp.evaluation.report import evaluate_run
from s3o_warp.provenance import REPO, cpu_name, git_commit, versions


def control_run(seq: Path, run: Path, frozen: bool) -> Path:
    """A run folder whose prediction is the ground truth itself, or the ground truth's first pose in every frame."""
    gt = load_ground_truth(seq / "ground_truth")
    names = np.array(sorted(p.stem for p in (seq / "masks").iterdir() if p.suffix == ".png"))
    sel = np.zeros(len(names), int) if frozen else np.arange(len(names))
    run.mkdir(parents=True, exist_ok=True)
    np.savez(run / "motion.npz", verts_cam=gt.verts[sel], faces=gt.faces, K=gt.K, image_size=np.array(gt.image_size),
             frame_names=names, joints_cam=gt.joints[sel])
    return run


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=list(SYNTH))
    ap.add_argument("--out-dir", default=str(REPO / "runs" / "bench"))
    args = ap.parse_args(argv)
    work = Path(args.out_dir)
    rows = []
    for case in args.cases:
        seq = prepare_case(case, work)
        if seq is None:
            continue
        for name, frozen in (("truth", False), ("frozen_first_pose", True)):
            t0 = time.perf_counter()
            m = evaluate_run(control_run(seq, work / "controls" / f"{case}-{name}", frozen), seq, progress=False)
            row = {"case": case, "control": name, "iou": m["mask_iou"]["mean"], "fscore": m["shape_3d"]["fscore"],
                   **views_figures(m), "eval_seconds": round(time.perf_counter() - t0, 1)}
            print(json.dumps(row), flush=True)
            rows.append(row)
    command = " ".join(["python", "scripts/bench_views.py"] + sys.argv[1:]).replace(args.out_dir, "OUT_DIR")
    doc = {"command": command, "device": "cpu",
           "device_name": cpu_name(), "versions": versions(), "git_commit": git_commit(), "results": rows}
    dest = REPO / "benchmarks" / "views-controls.json"
    write_text(dest, json.dumps(doc, indent=2))
    print(f"wrote {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
