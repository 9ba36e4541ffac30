#!/usr/bin/env python
"""Long-gap flow benchmark: direct DIS, composed chains and their per-pixel pick against the true flow, per gap.

    python scripts/bench_long_flow.py [--cases fox120 horse robot] [--gaps 1 2 4 8 16 32] [--crop-size S]
                                      [--conf 0.5] [--out-dir DIR]

The true flow comes from the sequence's ``ground_truth/``, rendered in crop pixels: each frame is z-buffered at the
crop's resolution with the crop's intrinsics ``inv(crop_to_frame) @ K``
(:func:`s3o_warp.evaluation.image.render_frames`), so every crop-t pixel on the object is a barycentric point of a
face visible in frame t; the same point at t + g, projected with crop t + g's intrinsics, is where it goes (crop
pixels, the unit of the fit's flow). A point is *occluded in the target* when the render of t + g at its pixel is
nearer by more than 2 % of its depth; those pixels are left out of every figure and their share is reported
(``occluded``). Points that leave crop t + g are kept.

Per case, gap and method (``direct``: DIS on the pair with the background blanked; ``composed``: the cached flows of
two half gaps chained; ``pick``: per pixel the more confident of the two; ``cached``: what
:func:`s3o_warp.data.long_flow.compute_long_flow` keeps, the pick up to ``DIRECT_MAX_GAP`` and the chain beyond;
gap 1 is the consecutive flow for all four): ``epe`` (mean end-point error, crop pixels, over the object's pixels
visible in both frames), ``epe_median``, ``confident`` (share of those pixels with confidence > ``--conf``) and
``epe_confident`` (mean EPE over them), forward direction. Times: today's consecutive flow
(:func:`s3o_warp.data.flow.compute_flow`) and the long-gap flow with all gaps (gap 1 included), each on an empty
cache, and their ratio; a second long-gap call on the filled cache (``cached_s``); wall-clock and process CPU
seconds (``*_cpu_s``: steadier on a shared machine). Written to ``benchmarks/long-flow-cpu.json`` with the command,
the machine and the versions.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from s3o_warp.config import DataConfig, make_config
from s3o_warp.data.flow import FLOW_FINEST_SCALE, compute_flow, make_dis
from s3o_warp.data.io import write_json
from s3o_warp.data.long_flow import (
    DIRECT_MASK_MARGIN,
    DIRECT_MAX_GAP,
    LONG_FLOW_GAPS,
    compose_pairs,
    compute_long_flow,
    direct_pair,
    hop_split,
    pick_pairs,
)
from s3o_warp.data.sequence import open_sequence
from s3o_warp.evaluation.image import render_frames
from s3o_warp.evaluation.loaders import load_ground_truth
from s3o_warp.geometry import project_np
from s3o_warp.provenance import REPO, cpu_name, git_commit, versions

OCCLUSION_DEPTH = 0.02
"""A point is occluded in the target frame when the surface rendered there is nearer by this share of its depth."""

METHODS = ("direct", "composed", "pick", "cached")


def _bench_fit():
    spec = importlib.util.spec_from_file_location("bench_fit", Path(__file__).with_name("bench_fit.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


class CropTruth:
    """Z-buffer renders of the true mesh in every frame's crop, and the true crop flow between two frames."""

    def __init__(self, verts: np.ndarray, faces: np.ndarray, K: np.ndarray, crop_to_frame: np.ndarray, crop_size: int):
        self.verts = verts.astype(np.float64)
        self.faces = faces.astype(np.int64)
        self.Kc = np.linalg.inv(crop_to_frame) @ K  # crop intrinsics
        self.S = crop_size
        T = len(verts)
        self.fi = np.empty((T, crop_size, crop_size), np.int32)
        self.bary = np.empty((T, crop_size, crop_size, 3), np.float32)
        for start, fi, bary in render_frames(verts.astype(np.float32), faces, self.Kc.astype(np.float32),
                                             (crop_size, crop_size), progress=False):
            self.fi[start:start + len(fi)] = fi
            self.bary[start:start + len(fi)] = bary
        self.depth = np.full((T, crop_size, crop_size), np.inf)
        for t in range(T):
            fg = self.fi[t] >= 0
            self.depth[t][fg] = self._points(t, t, fg)[:, 2]

    def _points(self, t: int, u: int, fg: np.ndarray) -> np.ndarray:
        """Camera-u positions of the surface points seen at crop-t pixels ``fg``."""
        tri = self.faces[self.fi[t][fg]]
        return (self.verts[u][tri] * self.bary[t][fg][..., None]).sum(1)

    def flow(self, t: int, u: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """True crop flow t -> u: ``(S, S, 2)``, the object's pixels in crop t ``(S, S)`` and those of them occluded in
        frame u."""
        S = self.S
        fg = self.fi[t] >= 0
        r, c = np.nonzero(fg)
        P = self._points(t, u, fg)
        q = project_np(P, self.Kc[u])
        flow = np.zeros((S, S, 2))
        flow[fg] = q - np.stack([c, r], 1)
        qi = np.round(q).astype(int)
        inside = (qi >= 0).all(1) & (qi < S).all(1)
        occ = np.zeros(len(P), bool)
        zq = self.depth[u][qi[inside, 1], qi[inside, 0]]
        occ[inside] = zq < P[inside, 2] * (1 - OCCLUSION_DEPTH)
        occluded = np.zeros((S, S), bool)
        occluded[r[occ], c[occ]] = True
        return flow, fg, occluded


def _stats(err: np.ndarray, conf: np.ndarray, threshold: float) -> dict:
    sure = conf > threshold
    return {"epe": float(err.mean()), "epe_median": float(np.median(err)), "confident": float(sure.mean()),
            "epe_confident": float(err[sure].mean()) if sure.any() else None}


def measure(seq_dir: Path, gaps: tuple[int, ...], crop_size: int, threshold: float) -> list[dict]:
    """Rows of one case: the flows' figures per gap and method, and the times."""
    cfg = DataConfig(crop_size=crop_size)
    seq = open_sequence(seq_dir, cfg=cfg)
    T = seq.num_frames
    gaps = tuple(g for g in gaps if g < T)
    split = hop_split(gaps)
    gt = load_ground_truth(seq_dir / "ground_truth")
    if gt.K is None or gt.image_size is None:
        raise SystemExit(f"bench_long_flow: {seq_dir / 'ground_truth'} lacks K or image_size; re-render it with "
                         "make_synthetic.py")
    K = np.broadcast_to(gt.K, (T, 3, 3))
    truth = CropTruth(gt.verts, gt.faces, K, seq.crop_to_frame, crop_size)
    with tempfile.TemporaryDirectory() as tmp:
        t0, c0 = time.perf_counter(), time.process_time()
        compute_flow(seq, Path(tmp) / "today", cfg)
        today_s, today_cpu = time.perf_counter() - t0, time.process_time() - c0
        t0, c0 = time.perf_counter(), time.process_time()
        cache = compute_long_flow(seq, Path(tmp) / "long", gaps, cfg)
        long_s, long_cpu = time.perf_counter() - t0, time.process_time() - c0
        t0 = time.perf_counter()
        compute_long_flow(seq, Path(tmp) / "long", gaps, cfg)
        cached_s = time.perf_counter() - t0
        dis = make_dis(cfg.flow_preset, FLOW_FINEST_SCALE)
        rows = []
        for g in gaps:
            acc = {m: ([], []) for m in METHODS}
            n_obj = n_occ = 0
            for t in range(T - g):
                flow_true, fg, occluded = truth.flow(t, t + g)
                use = fg & ~occluded
                n_obj += int(fg.sum())
                n_occ += int(occluded.sum())
                pick = np.asarray(np.load(cache.files[g][t], mmap_mode="r"))
                if g == 1:
                    arrays = {m: pick for m in METHODS}
                else:
                    a, b = split[g]
                    arrays = {
                        "direct": direct_pair(seq, t, t + g, dis),
                        "composed": compose_pairs(np.load(cache.files[a][t], mmap_mode="r"),
                                                  np.load(cache.files[b][t + a], mmap_mode="r")),
                        "cached": pick,
                    }
                    arrays["pick"] = pick_pairs(arrays["direct"], arrays["composed"])
                for m, arr in arrays.items():
                    acc[m][0].append(np.linalg.norm(arr[..., 0:2][use] - flow_true[use], axis=1))
                    acc[m][1].append(arr[..., 4][use])
            row = {"gap": g, "pairs": T - g, "occluded": n_occ / max(n_obj, 1)}
            for m in METHODS:
                row[m] = _stats(np.concatenate(acc[m][0]), np.concatenate(acc[m][1]), threshold)
            rows.append(row)
    times = {"today_s": today_s, "long_s": long_s, "ratio": long_s / today_s, "today_cpu_s": today_cpu,
             "long_cpu_s": long_cpu, "ratio_cpu": long_cpu / today_cpu, "cached_s": cached_s}
    return times, rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=["fox120", "horse", "robot"], help="synthetic cases of bench_fit.py")
    ap.add_argument("--gaps", nargs="+", type=int, default=list(LONG_FLOW_GAPS), help="gaps (frames), 1 included")
    ap.add_argument("--crop-size", type=int, default=None, help="data.crop_size (default: the default preset's)")
    ap.add_argument("--conf", type=float, default=0.5, help="confidence over which a pixel counts as confident")
    ap.add_argument("--out-dir", default=str(REPO / "runs" / "bench"),
                    help="where sequences are rendered (bench_fit.py's)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    if args.crop_size is None:
        args.crop_size = make_config("default").data.crop_size
    bf = _bench_fit()
    bad = [c for c in args.cases if c not in bf.SYNTH]
    if bad:
        print(f"bench_long_flow: --cases {' '.join(bad)} have no ground truth; choose from {', '.join(bf.SYNTH)}",
              file=sys.stderr)
        return 2
    try:
        hop_split(args.gaps)
    except Exception as exc:
        print(f"bench_long_flow: --gaps: {exc}", file=sys.stderr)
        return 2
    dest = REPO / "benchmarks" / "long-flow-cpu.json"
    doc = {"command": bf.command_line(args.out_dir), "device": "cpu", "device_name": cpu_name(),
           "cpu_count": os.cpu_count(), "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
           "versions": {**versions(), "opencv": cv2.__version__}, "git_commit": git_commit(),
           "crop_size": args.crop_size, "conf_threshold": args.conf, "occlusion_depth": OCCLUSION_DEPTH,
           "direct_max_gap": DIRECT_MAX_GAP, "direct_mask_margin": DIRECT_MASK_MARGIN,
           "results": []}
    for case in args.cases:
        seq = bf.prepare_case(case, Path(args.out_dir))
        if seq is None:
            continue
        times, rows = measure(seq, tuple(sorted(set(args.gaps))), args.crop_size, args.conf)
        res = {"case": case, **times, "gaps": rows}
        print(json.dumps(res), flush=True)
        doc["results"].append(res)
    write_json(dest, doc, indent=1)
    print(f"wrote {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
