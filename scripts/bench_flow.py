#!/usr/bin/env python
"""Optical-flow benchmark: how much of the true motion the fit's crop flow sees, on synthetic sequences.

    python scripts/bench_flow.py --cases fox120 horse [quadruped] [--finest-scales preset 0]
                                 [--presets medium] [--crop-size S] [--out-dir DIR]

The true flow comes from the sequence's ``ground_truth/``: each foreground pixel of frame t is a point on a
face (z-buffer render of the true mesh, :func:`s3o_warp.evaluation.image.render_frames`); the same barycentric point
on the face at t+1, projected, is where it goes. The measured flow is what a fit uses: the crop flow of
:func:`s3o_warp.data.flow.pair_flow` (DIS on the pair's canvas), taken back to frame pixels. Per pair and
setting: ``ratio``, the median over foreground crop pixels of (measured . true) / |true|^2 (1 = the full
motion; under 1: the motion is underestimated), the same
weighted by |true|^2 (``ratio_weighted``: dominated by the fastest parts, the legs), and ``epe`` (median
end-point error, frame pixels). Pixels that move under half a pixel are left out. Results are written to
``benchmarks/flow-cpu.json`` with the command, the machine and the versions.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import os
import sys
from pathlib import Path

import numpy as np

from s3o_warp.config import DataConfig, make_config
from s3o_warp.data.crops import map_points
from s3o_warp.data.flow import FLOW_FB_SIGMA, make_dis, pair_flow
from s3o_warp.data.io import write_json
from s3o_warp.data.sequence import open_sequence
from s3o_warp.evaluation.image import render_frames
from s3o_warp.evaluation.loaders import load_ground_truth
from s3o_warp.geometry import project_np
from s3o_warp.provenance import REPO, cpu_name, git_commit, versions


def _bench_fit():
    spec = importlib.util.spec_from_file_location("bench_fit", Path(__file__).with_name("bench_fit.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def true_frame_flow(verts: np.ndarray, faces: np.ndarray, K: np.ndarray, size: tuple[int, int]):
    """Per frame t < T-1: ``(H, W, 2)`` true flow t -> t+1 in frame pixels and ``(H, W)`` foreground."""
    out = []
    for start, fi, bary in render_frames(verts[:-1], faces, K[:-1], size, progress=False):
        for k in range(fi.shape[0]):
            t = start + k
            fg = fi[k] >= 0
            tri = faces[fi[k][fg]]  # (P, 3) vertex indices
            b = bary[k][fg][..., None]
            x0 = project_np((verts[t][tri] * b).sum(1), K[t])
            x1 = project_np((verts[t + 1][tri] * b).sum(1), K[t + 1])
            flow = np.zeros(size + (2,), np.float64)
            flow[fg] = x1 - x0
            out.append((flow, fg))
    return out


def measure(seq_dir: Path, preset: str, finest_scale: int | None, crop_size: int, truth) -> dict:
    """Ratio and end-point error of the crop flow against ``truth`` (from :func:`true_frame_flow`)."""
    cfg = DataConfig(crop_size=crop_size, flow_preset=preset)
    seq = open_sequence(seq_dir, cfg=cfg)
    dis = make_dis(preset, finest_scale)
    c2f = seq.crop_to_frame
    S = crop_size
    r, c = np.mgrid[0:S, 0:S].astype(np.float64)
    p = np.stack([c, r], -1)
    ratios, weighted, epes = [], [], []
    for t, (ftrue, fg) in enumerate(truth):
        arr = pair_flow(seq.image(t), seq.image(t + 1), c2f[t], c2f[t + 1], S, FLOW_FB_SIGMA, dis)
        x = map_points(p, c2f[t])  # crop-t pixels in frame t
        x2 = map_points(p + arr[..., 0:2], c2f[t + 1])  # where the flow sends them, frame t+1
        xi, yi = np.round(x[..., 0]).astype(int), np.round(x[..., 1]).astype(int)
        H, W = fg.shape
        ok = (xi >= 0) & (yi >= 0) & (xi < W) & (yi < H)
        ok[ok] = fg[yi[ok], xi[ok]]
        g = ftrue[yi[ok], xi[ok]]
        m = (x2 - x)[ok]
        moving = (g * g).sum(1) > 0.25
        g, m = g[moving], m[moving]
        if len(g) < 20:
            continue
        n2 = (g * g).sum(1)
        ratios.append(float(np.median((m * g).sum(1) / n2)))
        weighted.append(float((m * g).sum() / n2.sum()))
        epes.append(float(np.median(np.linalg.norm(m - g, axis=1))))
    return {"pairs": len(ratios), "ratio": float(np.median(ratios)), "ratio_q10": float(np.percentile(ratios, 10)),
            "ratio_weighted": float(np.median(weighted)), "epe": float(np.median(epes))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=["fox120", "horse"], help="synthetic cases of bench_fit.py")
    ap.add_argument("--presets", nargs="+", default=["medium"], help="DIS presets (data.flow_preset)")
    ap.add_argument("--finest-scales", nargs="+", default=["preset", "0"],
                    help="DIS finest pyramid levels; 'preset' = the preset's own (the fit's: FLOW_FINEST_SCALE)")
    ap.add_argument("--crop-size", type=int, default=None, help="data.crop_size (default: the default preset's)")
    ap.add_argument("--out-dir", default=str(REPO / "runs" / "bench"), help="where sequences are rendered (bench_fit.py's)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    if args.crop_size is None:
        args.crop_size = make_config("default").data.crop_size

    bf = _bench_fit()
    dest = REPO / "benchmarks" / "flow-cpu.json"
    doc = {"command": " ".join(["python"] + sys.argv), "device": "cpu", "device_name": cpu_name(),
           "cpu_count": os.cpu_count(), "versions": versions(), "git_commit": git_commit(), "results": []}
    for case in args.cases:
        if case not in bf.SYNTH:
            raise SystemExit(f"bench_flow: {case} has no ground truth; choose from {', '.join(bf.SYNTH)}")
        seq = bf.prepare_case(case, Path(args.out_dir))
        if seq is None:
            continue
        gt = load_ground_truth(seq / "ground_truth")
        if gt.K is None or gt.image_size is None:
            raise SystemExit(f"bench_flow: {seq / 'ground_truth'} lacks K or image_size; re-render it with make_synthetic.py")
        truth = true_frame_flow(gt.verts, gt.faces, gt.K, tuple(int(v) for v in gt.image_size))
        for preset in args.presets:
            for fs in args.finest_scales:
                finest = None if fs == "preset" else int(fs)
                res = {"case": case, "preset": preset, "finest_scale": finest, "crop_size": args.crop_size,
                       **measure(seq, preset, finest, args.crop_size, truth)}
                print(json.dumps(res), flush=True)
                doc["results"].append(res)
    write_json(dest, doc, indent=1)
    print(f"wrote {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
