#!/usr/bin/env python
"""Peak memory of a fit against the video length: ``benchmarks/memory-<device>.json``.

    python scripts/bench_memory.py --device cpu --frames 100 1000 [--size 320x240] [--steps 40]

For each length a synthetic quadruped sequence is rendered (once, cached under --work), then a short
fit (``--steps`` per phase, the default crop size) runs in a child process whose peak resident memory
(``ru_maxrss``) is recorded. Sequences longer than ``data.resident_max_frames`` stream their crops and
flow from disk, so the peak should grow with the batch and the resolution, not with the length.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from s3o_warp.data.io import write_text
from s3o_warp.provenance import REPO, device_name, git_commit, versions
from s3o_warp.synth import make_sequence

CHILD = r"""
import resource, sys, json, time, torch
from pathlib import Path
from s3o_warp.config import make_config
from s3o_warp.fit import fit, resolve_device
seq, run, steps, device = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
cfg = make_config("default", overrides=[f"coarse.steps={steps}", f"motion.warmup_steps={steps}", f"motion.steps={steps}",
                                        "output.render_video=false"])
t0 = time.perf_counter()
m = fit(seq, run, cfg, resolve_device(device))
print(json.dumps({"seconds": time.perf_counter() - t0, "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "iou": (m.get("mask_iou") or {}).get("mean")}))
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--frames", nargs="+", type=int, default=[100, 1000])
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--work", default=str(REPO / "runs" / "bench-memory"))
    args = ap.parse_args(argv)
    W, H = (int(x) for x in args.size.lower().split("x"))
    work = Path(args.work)
    results = []
    for n in args.frames:
        seq = work / f"quadruped-{n}"
        if not (seq / "images").is_dir():
            t0 = time.perf_counter()
            make_sequence(seq, frames=n, size=(W, H), azim=(-30.0, 30.0))
            print(f"rendered {n} frames in {time.perf_counter() - t0:.0f} s", flush=True)
        run = work / f"run-{n}"
        out = subprocess.run([sys.executable, "-c", CHILD, str(seq), str(run), str(args.steps), args.device],
                             capture_output=True, text=True, cwd=REPO)
        if out.returncode != 0:
            print(out.stderr[-2000:], file=sys.stderr)
            return out.returncode
        rec = json.loads(out.stdout.strip().splitlines()[-1])
        rec.update(frames=n, size=[W, H], steps_per_phase=args.steps)
        results.append(rec)
        print(json.dumps(rec), flush=True)
    doc = {
        "command": " ".join(["python"] + sys.argv),
        "device": args.device,
        "device_name": device_name(args.device),
        "versions": versions(),
        "git_commit": git_commit(),
        "note": "peak_rss_mb is the child process's ru_maxrss (includes Python, torch and Warp: about 400-500 MB at rest)",
        "results": results,
    }
    dest = REPO / "benchmarks" / f"memory-{args.device.split(':')[0]}.json"
    write_text(dest, json.dumps(doc, indent=2))
    print(f"wrote {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
