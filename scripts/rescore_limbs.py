#!/usr/bin/env python
"""Score finished synthetic fits' limb counts again with the current metrics, beside what their own
``metrics.json`` says (for example after the counts started following each limb on to its end joint's tip).

    python scripts/rescore_limbs.py RUN_DIR:SEQUENCE_DIR [RUN_DIR:SEQUENCE_DIR ...] [--out FILE]

Each run is evaluated as ``scripts/evaluate.py`` would (:func:`s3o_warp.evaluation.metrics.evaluate_run`, written to
``RUN_DIR/metrics-rescored.json``, the run's own ``metrics.json`` left as it is). One row per run goes to
``--out`` (default ``benchmarks/limbs-rescore-cpu.json``) with the command, the machine and the versions: per
limb count (``limbs``, ``limbs_distinct``, ``limbs_framewise``) the covered limbs and each limb's ``tol_needed``,
before (the run's ``metrics.json``) and now.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

from s3o_warp.errors import InputError
from s3o_warp.data.io import read_json
from s3o_warp.evaluation.metrics import evaluate_run, write_json, write_metrics
from s3o_warp.provenance import REPO, cpu_name, git_commit, versions

COUNTS = ("limbs", "limbs_distinct", "limbs_framewise")


def summary(metrics: dict) -> dict:
    """Per limb count: ``covered``, ``total``, ``to_tip`` and ``{limb: tol_needed}``."""
    out = {}
    for k in COUNTS:
        c = (metrics.get("skeleton") or {}).get(k)
        if c:
            out[k] = {"covered": c["covered"], "total": c["total"], "to_tip": bool(c.get("to_tip", False)),
                      "tol_needed": {lim["limb"]: lim["tol_needed"] for lim in c["limbs"]}}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("pairs", nargs="+", metavar="RUN_DIR:SEQUENCE_DIR")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "limbs-rescore-cpu.json"))
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    rows = []
    for pair in args.pairs:
        run, sep, seq = pair.partition(":")
        if not sep:
            print(f"error: {pair!r}: give RUN_DIR:SEQUENCE_DIR", file=sys.stderr)
            return 2
        run, seq = Path(run), Path(seq)
        try:
            before = read_json(run / "metrics.json", "the run's metrics", "rerun scripts/evaluate.py on it, or move the "
                               "broken file away") if (run / "metrics.json").is_file() else {}
            now = evaluate_run(run, seq, progress=False)
        except InputError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        write_metrics(now, run / "metrics-rescored.json")
        rows.append({"run": str(run), "sequence": str(seq), "pck_t": (now.get("pck_t") or {}).get("pck"),
                     "before": summary(before), "now": summary(now)})
        print(json.dumps({"run": str(run), **{k: f"{v['covered']}/{v['total']}" for k, v in summary(now).items()}}),
              flush=True)
    write_json({"command": " ".join(["python"] + sys.argv), "device": "cpu", "device_name": cpu_name(),
                "cpu_count": os.cpu_count(), "versions": versions(), "git_commit": git_commit(), "results": rows},
               args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
