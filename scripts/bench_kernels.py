#!/usr/bin/env python
"""Kernel benchmark: each Warp op beside its dense torch twin (and the naive O(P x F) silhouette).

    python scripts/bench_kernels.py --device cpu|cuda [--repeats N] [--quick]

Prints a table and writes ``benchmarks/kernels-<device>.json`` with the command, device name, versions,
git commit and, per case, its parameters and the median / p90 milliseconds of repeated runs (after a
warm-up; CUDA is synchronised inside the timed closure). Setup happens outside the timed closures.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch
import trimesh
from s3o_warp.kernels import nearest, raster, regularisers, skinning, visibility

from s3o_warp.data.io import write_text
from s3o_warp.provenance import REPO, git_commit, versions
from s3o_warp.reference import nearest as rnear
from s3o_warp.reference import raster as rraster
from s3o_warp.reference import regularisers as rreg
from s3o_warp.reference import skinning as rskin


def timeit(fn, device: str, repeats: int, warmup: int = 1) -> dict:
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(repeats):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        ts.append((time.perf_counter() - t0) * 1000)
    ts.sort()
    return {"median_ms": round(statistics.median(ts), 3), "p90_ms": round(ts[min(len(ts) - 1, int(0.9 * len(ts)))], 3), "runs": len(ts)}


def fwd_bwd(op, inputs: list[torch.Tensor]):
    """A closure running op(*inputs) and a backward of a random-weighted sum of its output."""
    def run():
        for x in inputs:
            if isinstance(x, torch.Tensor) and x.requires_grad:
                x.grad = None
        out = op()
        out = out[0] if isinstance(out, tuple) else out
        g = torch.ones_like(out) if out.dim() == 0 else torch.linspace(0.5, 1.5, out.numel(), device=out.device).reshape(out.shape)
        (out * g).sum().backward()
    return run


def sphere(subdiv: int, device: str, radius=1.0, depth=3.0):
    m = trimesh.creation.icosphere(subdivisions=subdiv, radius=radius)
    v = torch.tensor(m.vertices, dtype=torch.float32, device=device)
    v[:, 2] += depth
    f = torch.tensor(m.faces, dtype=torch.int64, device=device)
    return v, f


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="smaller naive-silhouette case (fewer frames), scaled")
    args = ap.parse_args(argv)
    dev = args.device
    if dev.startswith("cuda") and not torch.cuda.is_available():
        print("bench_kernels: --device cuda but no CUDA device is visible; use --device cpu", file=sys.stderr)
        return 2

    cases = []

    def add(name, params, impl, fn, reps=None):
        r = timeit(fn, dev, reps or args.repeats)
        cases.append({"op": name, "impl": impl, **params, **r})
        print(f"{name:28s} {impl:22s} {json.dumps(params):60s} median {r['median_ms']:10.2f} ms  p90 {r['p90_ms']:10.2f} ms", flush=True)

    # --- soft silhouette: 256x256, 5k faces (icosphere level 4 = 5120 faces), 8 frames --------------
    H = W = 256
    T = 8
    v, f = sphere(4, dev)
    K = torch.tensor([[300.0, 0, 127.5], [0, 300.0, 127.5], [0, 0, 1]], device=dev)
    vt = v.expand(T, -1, -1).clone()
    vt += 0.02 * torch.randn_like(vt)
    vt.requires_grad_(True)
    p = {"H": H, "W": W, "F": int(f.shape[0]), "T": T, "sigma": 1.0}
    add("soft_silhouette fwd", p, "warp_binned", lambda: raster.soft_silhouette(vt, f, K, (H, W), sigma=1.0))
    add("soft_silhouette fwd+bwd", p, "warp_binned", fwd_bwd(lambda: raster.soft_silhouette(vt, f, K, (H, W), sigma=1.0), [vt]))
    # naive O(P x F): on the CPU one frame at a time and scaled to T frames (it takes seconds per frame)
    Tn = 1 if (dev == "cpu" or args.quick) else T
    vn = vt[:Tn].detach().clone().requires_grad_(True)
    pn = dict(p, T=Tn, scaled_to_T=T)
    r = timeit(fwd_bwd(lambda: raster.soft_silhouette_naive(vn, f, K, (H, W), sigma=1.0), [vn]), dev, max(1, min(3, args.repeats)), warmup=0)
    for k in ("median_ms", "p90_ms"):
        r[k] = round(r[k] * T / Tn, 3)
    cases.append({"op": "soft_silhouette fwd+bwd", "impl": "warp_naive_O(PxF)", **pn, **r})
    print(f"{'soft_silhouette fwd+bwd':28s} {'warp_naive_O(PxF)':22s} {json.dumps(pn):60s} median {r['median_ms']:10.2f} ms (scaled)", flush=True)
    # dense torch twin at a smaller size (it is O(P x F) memory)
    vs, fs = sphere(2, dev)
    vs = vs.expand(2, -1, -1).clone().requires_grad_(True)
    Hs = Ws = 64
    Ks = torch.tensor([[80.0, 0, 31.5], [0, 80.0, 31.5], [0, 0, 1]], device=dev)
    ps = {"H": Hs, "W": Ws, "F": int(fs.shape[0]), "T": 2, "sigma": 1.0}
    add("soft_silhouette fwd+bwd", ps, "torch_dense_twin", fwd_bwd(lambda: rraster.soft_silhouette_reference(vs, fs, Ks, (Hs, Ws), sigma=1.0), [vs]))
    add("soft_silhouette fwd+bwd", ps, "warp_binned", fwd_bwd(lambda: raster.soft_silhouette(vs, fs, Ks, (Hs, Ws), sigma=1.0), [vs]))

    # --- rasterize + interpolate --------------------------------------------------------------------
    attr = torch.rand(v.shape[0], 3, device=dev, requires_grad=True)

    def ras_interp():
        fi, bary, depth = raster.rasterize(vt, f, K, (H, W))
        return raster.interpolate(attr, f, fi, bary)

    add("rasterize+interpolate fwd+bwd", p, "warp", fwd_bwd(ras_interp, [vt, attr]))

    # --- skinning: N=5000, B=25, T=8 ---------------------------------------------------------------
    N, B, T = 5000, 25, 8
    X = torch.randn(N, 3, device=dev, requires_grad=True)
    C = torch.randn(B, 3, device=dev, requires_grad=True)
    A = torch.randn(B, 3, 3, device=dev)
    Q = (A @ A.transpose(1, 2) + torch.eye(3, device=dev)).requires_grad_(True)
    Wt = torch.softmax(torch.randn(N, B, device=dev), 1).requires_grad_(True)
    brt = torch.randn(T, B, 3, 4, device=dev, requires_grad=True)
    rrt = torch.randn(T, 3, 4, device=dev, requires_grad=True)
    ps = {"N": N, "B": B, "T": T}
    add("skinning_weights fwd+bwd", ps, "warp", fwd_bwd(lambda: skinning.skinning_weights(X, C, Q), [X, C, Q]))
    add("skinning_weights fwd+bwd", ps, "torch_twin", fwd_bwd(lambda: rskin.skinning_weights_reference(X, C, Q), [X, C, Q]))
    add("blend_skinning fwd", ps, "warp", lambda: skinning.blend_skinning(X, Wt, brt, rrt))
    add("blend_skinning fwd", ps, "torch_einsum_twin", lambda: rskin.blend_skinning_reference(X, Wt, brt, rrt))
    add("blend_skinning fwd+bwd", ps, "warp", fwd_bwd(lambda: skinning.blend_skinning(X, Wt, brt, rrt), [X, Wt, brt, rrt]))
    add("blend_skinning fwd+bwd", ps, "torch_einsum_twin", fwd_bwd(lambda: rskin.blend_skinning_reference(X, Wt, brt, rrt), [X, Wt, brt, rrt]))

    # --- regularisers at N ~ 2562 (icosphere level 4) ----------------------------------------------
    v4, f4 = sphere(4, dev, depth=0.0)
    edges = regularisers.mesh_edges(f4)
    Tr = 8
    vv = (v4.expand(Tr, -1, -1) + 0.01 * torch.randn(Tr, v4.shape[0], 3, device=dev)).requires_grad_(True)
    Wr = torch.softmax(torch.randn(v4.shape[0], 25, device=dev), 1).requires_grad_(True)
    pr = {"N": int(v4.shape[0]), "E": int(edges.shape[0]), "T": Tr}
    add("dynamic_rigidity fwd+bwd", pr, "warp", fwd_bwd(lambda: regularisers.dynamic_rigidity_loss(vv, edges, Wr), [vv, Wr]))
    add("dynamic_rigidity fwd+bwd", pr, "torch_twin", fwd_bwd(lambda: rreg.dynamic_rigidity_loss_reference(vv, edges, Wr), [vv, Wr]))
    v0 = v4.clone().requires_grad_(True)
    plane = (torch.tensor([0.0, 0.0, 1.0], device=dev), 0.0)
    add("laplacian fwd+bwd", pr, "warp", fwd_bwd(lambda: regularisers.laplacian_loss(v0, f4), [v0]))
    add("laplacian fwd+bwd", pr, "torch_twin", fwd_bwd(lambda: rreg.laplacian_loss_reference(v0, f4), [v0]))
    add("symmetry fwd+bwd", pr, "warp", fwd_bwd(lambda: regularisers.symmetry_loss(v0, plane), [v0]))
    add("symmetry fwd+bwd", pr, "torch_twin", fwd_bwd(lambda: rreg.symmetry_loss_reference(v0, plane), [v0]))

    # --- visibility: N ~ 2562, F = 5120, T = 8 -----------------------------------------------------
    vis_v = v4.expand(8, -1, -1).clone()
    vis_v[..., 2] += 3.0
    pv = {"N": int(v4.shape[0]), "F": int(f4.shape[0]), "T": 8}
    add("vertex_visibility", pv, "warp_bvh_refit", lambda: visibility.vertex_visibility(vis_v, f4))

    # --- nearest projected vertex per uncovered pixel (the coverage loss): Q = 256 x 8, N ~ 2562, T = 8 ---
    g = torch.Generator().manual_seed(0)
    pts = (torch.rand(8, int(v4.shape[0]), 2, generator=g) * 192).to(dev)
    qs = (torch.rand(256 * 8, 2, generator=g) * 192).to(dev)
    qf = torch.arange(8).repeat_interleave(256).to(dev)
    pn = {"Q": int(qs.shape[0]), "N": int(pts.shape[1]), "T": 8}
    add("nearest_point", pn, "warp_brute_force", lambda: nearest.nearest_point(qs, qf, pts))
    add("nearest_point", pn, "torch_dense_twin", lambda: rnear.nearest_point_reference(qs, qf, pts))

    out = {
        "command": " ".join([Path(sys.executable).name] + sys.argv),
        "device": dev,
        "device_name": torch.cuda.get_device_name(dev) if dev.startswith("cuda") else platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "versions": versions(),
        "git_commit": git_commit(),
        "cases": cases,
    }
    summary = _summary(cases)
    out["summary"] = summary
    print(json.dumps(summary, indent=2))
    dest = REPO / "benchmarks" / f"kernels-{dev.split(':')[0]}.json"
    dest.parent.mkdir(exist_ok=True)
    write_text(dest, json.dumps(out, indent=2))
    print(f"wrote {dest}")
    return 0


def _summary(cases):
    def med(op, impl, **kw):
        for c in cases:
            if c["op"] == op and c["impl"] == impl and all(c.get(k) == v for k, v in kw.items()):
                return c["median_ms"]
        return None

    s = {}
    b = med("soft_silhouette fwd+bwd", "warp_binned", H=256)
    n = med("soft_silhouette fwd+bwd", "warp_naive_O(PxF)")
    if b and n:
        s["silhouette_binned_speedup_vs_naive_256px_5kF_T8"] = round(n / b, 1)
    w = med("blend_skinning fwd+bwd", "warp")
    t = med("blend_skinning fwd+bwd", "torch_einsum_twin")
    if w and t:
        s["blend_skinning_warp_over_torch_fwd_bwd_N5000_B25_T8"] = round(w / t, 2)
    return s


if __name__ == "__main__":
    sys.exit(main())
