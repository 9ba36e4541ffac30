#!/usr/bin/env python
"""What ``s3o-batch`` adds to the fits it runs: ``benchmarks/batch-<device>.json``.

    python scripts/bench_batch.py [--sequences 4] [--frames 16] [--size 128x96] [--preset smoke] [--set KEY=VALUE ...]
                                  [--work DIR]

Short synthetic quadruped sequences (one seed each, rendered once under --work) are fitted three times, each time by
a fresh process timed from its start to its exit: one after another by ``fit()`` in one Python process, then by
``s3o-batch`` on a local Ray (its start, the workers' imports, the tasks and the summary included), first with one
fit at a time on all CPUs (the loop's schedule), then with its default CPUs per fit. The overhead is
the batch's wall time over the loop's, minus one; each process's seconds outside its fits (the loop's around each
``fit()`` call, the batch's around each task) are recorded too. Each fit's mask IoU is recorded from both, to show the batch runs
the same fits. The machine's load average is recorded too: on a shared machine both walls move with it.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import ray

from s3o_warp.data.io import write_text
from s3o_warp.provenance import REPO, device_name, git_commit, versions
from s3o_warp.synth import make_sequence

LOOP = r"""
import json, sys, time
from pathlib import Path
from s3o_warp.config import make_config
from s3o_warp.fit import fit, resolve_device
seqs, runs, preset, sets = sys.argv[1], Path(sys.argv[2]), sys.argv[3], sys.argv[4:]
out = {}
for seq in sorted(p for p in Path(seqs).iterdir() if (p / "images").is_dir()):
    t0 = time.perf_counter()
    fit(seq, runs / seq.name, make_config(preset, overrides=sets), resolve_device("cpu"))
    out[seq.name] = round(time.perf_counter() - t0, 2)
print(json.dumps(out))
"""


def timed(cmd: list[str]) -> tuple[float, str]:
    """Wall seconds of ``cmd`` from start to exit, and its stdout."""
    t0 = time.perf_counter()
    out = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if out.returncode != 0:
        sys.exit(f"bench_batch: {' '.join(cmd[:3])}... failed ({out.returncode}):\n{out.stderr[-3000:]}")
    return wall, out.stdout


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", type=int, default=4)
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--size", default="128x96")
    ap.add_argument("--preset", default="smoke")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--work", default=str(REPO / "runs" / "bench-batch"))
    args = ap.parse_args(argv)
    W, H = (int(x) for x in args.size.lower().split("x"))
    work = Path(args.work)
    seqs = work / f"sequences-{args.frames}-{W}x{H}"
    for i in range(args.sequences):
        if not (seqs / f"quad{i}" / "images").is_dir():
            make_sequence(seqs / f"quad{i}", frames=args.frames, size=(W, H), azim=(-20.0, 20.0), seed=i, progress=False)
    shutil.rmtree(work / "loop", ignore_errors=True)
    sets = [s for kv in args.overrides for s in ("--set", kv)]
    load0 = os.getloadavg()
    loop_s, stdout = timed([sys.executable, "-c", LOOP, str(seqs), str(work / "loop"), args.preset, *args.overrides])
    loop_fit_s = json.loads(stdout.strip().splitlines()[-1])
    loop_iou = {p.name: json.loads((p / "metrics.json").read_text())["mask_iou"]["mean"]
                for p in sorted((work / "loop").iterdir())}
    rec = {
        "sequences": args.sequences, "frames": args.frames, "size": [W, H], "preset": args.preset,
        "overrides": args.overrides, "loop_wall_s": round(loop_s, 2),
        "loop_outside_fits_s": round(loop_s - sum(loop_fit_s.values()), 2), "batch": [],
        "load_average_1min": [round(load0[0], 2)],
    }
    # one fit at a time on every CPU (the loop's schedule: what the batch itself adds), then s3o-batch's default
    for arm, flags in (("one at a time", ["--cpus-per-fit", str(os.cpu_count())]), ("default", [])):
        out = work / ("batch-" + arm.replace(" ", "-"))
        shutil.rmtree(out, ignore_errors=True)
        batch_s, _ = timed([str(Path(sys.executable).parent / "s3o-batch"), str(seqs), "--out", str(out),
                            "--preset", args.preset, *sets, *flags])
        summary = json.loads((out / "summary.json").read_text())
        rec["batch"].append({
            "arm": arm, "flags": flags, "cpus_per_fit": summary.get("cpus_per_fit"), "wall_s": round(batch_s, 2),
            "overhead": round(batch_s / loop_s - 1, 4),
            # seconds outside the tasks: the imports, Ray's start and stop and the workers' imports (the loop's
            # outside its fit() calls: its imports), less moved by the machine's load than the walls
            "outside_fits_s": round(batch_s - sum(r["wall_s"] for r in summary["rows"]), 2),
            "fits": [{"name": r["name"], "status": r["status"], "loop_s": loop_fit_s.get(r["name"]),
                      "batch_task_s": r.get("wall_s"), "loop_iou": loop_iou.get(r["name"]),
                      "batch_iou": r.get("mask_iou")} for r in summary["rows"]],
        })
        rec["load_average_1min"].append(round(os.getloadavg()[0], 2))
    print(json.dumps(rec, indent=1))
    doc = {
        "command": " ".join(["python", "scripts/bench_batch.py", *sys.argv[1:]]),
        "device": "cpu",
        "device_name": device_name("cpu"),
        "versions": {**versions(), "ray": ray.__version__},
        "git_commit": git_commit(),
        "note": "wall = a fresh process from start to exit: the loop fits the sequences one after another in one "
                "process; the batch is s3o-batch on a local Ray (start, worker imports, tasks, summary), once with one fit at "
                "a time on all CPUs (the loop's schedule) and once with its default CPUs per fit. overhead = batch / "
                "loop - 1. load_average_1min: before the loop and after each batch (a shared machine). Runs and "
                "sequences under OUT_DIR (--work).",
        "results": [rec],
    }
    dest = REPO / "benchmarks" / "batch-cpu.json"
    write_text(dest, json.dumps(doc, indent=2) + "\n")
    print(f"wrote {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
