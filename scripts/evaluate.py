"""Score a fitted run: mask IoU, PCK-T (keypoints), 3D Chamfer / F-score and skeleton (ground truth).

Usage:
    python scripts/evaluate.py RUN_DIR_OR_MOTION_NPZ --sequence SEQ_DIR [--keypoints FILE]
        [--ground-truth DIR] [--masks DIR] [--out metrics.json]

Prints a table and writes ``metrics.json`` (atomically) into the run directory, or to ``--out``.
The logic is ``s3o_warp.evaluation.report.evaluate_run``; BADJA files convert with ``python -m s3o_warp.data.keypoints``.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from s3o_warp.errors import InputError
from s3o_warp.evaluation.report import evaluate_run, format_table, write_metrics


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="run directory (with motion.npz) or the motion.npz file")
    ap.add_argument("--sequence", required=True,
                    help="sequence folder (masks/, optional keypoints.json and ground_truth/)")
    ap.add_argument("--keypoints", help="keypoints.json (default: SEQ/keypoints.json when present)")
    ap.add_argument("--ground-truth", help="ground_truth/ folder or its .npz (default: SEQ/ground_truth when present)")
    ap.add_argument("--masks", help="masks folder (default: SEQ/masks), e.g. davis/Annotations/480p/cows")
    ap.add_argument("--object-id", type=int, help="palette index of the object in palette (DAVIS-2017) masks")
    ap.add_argument("--alpha", type=float, default=0.2, help="PCK-T threshold as a fraction of sqrt(mask area)")
    ap.add_argument("--threshold-frame", choices=("reference", "target"), default="reference",
                    help="whose mask area sets the PCK-T threshold (reference = LASR/ViSER)")
    ap.add_argument("--points", type=int, default=5000, help="surface samples per frame for Chamfer / F-score")
    ap.add_argument("--seed", type=int, default=0, help="surface-sampling seed")
    ap.add_argument("--device", default="cpu", help="torch device of the renders (cpu, cuda:0)")
    ap.add_argument("--chunk", type=int, default=8, help="frames per render call")
    ap.add_argument("--chain-separation", type=float, default=0.15,
                    help="limbs of distinct joints: joints closer than this fraction of the limb's length along it "
                         "count once")
    ap.add_argument("--no-limb-tips", action="store_true",
                    help="limb counts stop at each limb's end joint instead of going on to its tip (the ground "
                         "truth's <joint>_tip keypoint; how the older rows of benchmarks/fit-cpu.json were scored)")
    ap.add_argument("--out", help="where to write metrics.json (default: RUN_DIR/metrics.json)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        metrics = evaluate_run(
            args.run, args.sequence, keypoints=args.keypoints, ground_truth=args.ground_truth, masks=args.masks,
            object_id=args.object_id, alpha=args.alpha, threshold_frame=args.threshold_frame,
            n_points=args.points, seed=args.seed, chunk=args.chunk, device=args.device,
            chain_separation=args.chain_separation, limb_tips=not args.no_limb_tips,
        )
        run = Path(args.run)
        out = Path(args.out) if args.out else (run if run.is_dir() else run.parent) / "metrics.json"
        write_metrics(metrics, out)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(format_table(metrics))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
