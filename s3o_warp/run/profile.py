"""Where a fit's time goes: per phase, wall time, steps and a step split into Warp kernels, torch ops, host syncs
and Python (``scripts/bench_fit.py --profile``).

:class:`FitProfile` is a context manager that wraps, for as long as it is open, the functions a fit runs through
(the optical flow, the lift, each phase's step loop, the camera hypotheses and their scoring, the M-step, the
even resampling, checkpoints, export, metrics, renders) and ``warp.launch``; closed, it puts every one back, so a
fit without it pays nothing. Each stretch of time is charged to the innermost of those regions it falls in, so
the regions' walls add up to the fit's.

Regions with steps (coarse, hypotheses, warmup, joint) also get a sample: :data:`SAMPLE_STEPS` steps after the
first :data:`SAMPLE_SKIP` (fewer when another region, a checkpoint or the hypotheses' scoring, begins first) run
under ``torch.profiler``; the profiler's own start and reading are left out of every figure. A sample's wall time
per step is split into

- ``kernels``: time inside ``warp.launch`` (on the CPU the kernel runs inside the call; on CUDA the sample
  synchronises the device around each launch, so this is kernel time there too) and Warp BVH builds and refits;
- ``torch``: the self time of torch's operators (``aten::*``), less the syncs;
- ``syncs``: operators that wait for the device on a GPU (``.item()``/``float()`` on a tensor, ``nonzero``) and
  Warp stream synchronisations, with their count per step;
- ``python``: the rest (the interpreter, autograd's engine, the profiler's own overhead).

Phase totals (``kernels_s``, ``launches``) cover every step, not only the sample.
"""

from __future__ import annotations

import functools
import time
from collections import defaultdict

import torch
import warp as wp

SAMPLE_SKIP = 2
"""Steps of a region run before its sample starts (the first steps load kernels and allocate)."""
SAMPLE_STEPS = 10
"""Steps of each region's sample."""
SYNC_OPS = ("aten::_local_scalar_dense", "aten::nonzero")
"""Torch operators that make the host wait for the device (``.item()``, ``float(t)``, ``bool(t)``, ``nonzero``)."""


def _targets():
    """(owner, attribute, region) of every function wrapped; ``region`` None: a step-loop whose region is its phase
    argument. Imported here, so importing this module costs nothing."""
    from s3o_warp import fit as fit_mod
    from s3o_warp.data import store
    from s3o_warp.run import outputs, pictures

    F = fit_mod.Fitter
    return [
        (fit_mod, "prepare_data", "data"),
        (store, "compute_long_flow", "flow"),
        (fit_mod, "coarse_model", "lift"),
        (F, "__init__", "model setup"),
        (F, "run", "fit (between phases)"),
        (F, "_run_phase", None),
        (fit_mod, "select_hypotheses", "hypotheses"),
        (F, "mean_terms", "hypotheses: scoring"),
        (F, "flow_by_gap", "hypotheses: scoring"),
        (F, "hard_iou", "hard IoU"),
        (F, "resolve_crossings", "crossings"),
        (F, "_m_step", "m-step"),
        (F, "resample_mesh", "resample"),
        (fit_mod, "save_step", "checkpoints"),
        (fit_mod, "save_branch", "checkpoints"),
        (fit_mod.outputs, "write_run", "outputs"),
        (outputs, "rig_from_model", "export"),
        (outputs, "save_rig", "export"),
        (outputs, "export_usd", "export"),
        (outputs, "export_gltf", "export"),
        (outputs, "evaluate_run", "metrics"),
        (pictures, "write_renders", "renders"),
    ]


class _Region:
    def __init__(self):
        self.wall = 0.0
        self.steps = 0
        self.kernels = 0.0
        self.launches = 0
        self.calls = 0
        self.sample: dict | None = None


class FitProfile:
    """``with FitProfile(device) as prof: fit(...)``; then :meth:`report` gives the per-region figures."""

    def __init__(self, device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        self.regions: dict[str, _Region] = defaultdict(_Region)
        self.kernel_times: dict[str, list] = defaultdict(lambda: [0.0, 0])  # kernel key -> [seconds, launches]
        self._stack: list[str] = ["outside"]
        self._t = 0.0
        self._saved: list = []
        self._prof = None  # the running torch.profiler of a sample
        self._sampling: dict | None = None
        self.wall = 0.0
        self._overhead = 0.0

    # -- the region stack ---------------------------------------------------------------------------
    def _charge(self) -> None:
        now = time.perf_counter()
        self.regions[self._stack[-1]].wall += now - self._t
        self._t = now

    def _enter(self, name: str) -> None:
        if self._sampling is not None:  # a sample holds its region's steps only: it ends where another region begins
            self._stop_sample()
        self._charge()
        self._stack.append(name)
        self.regions[name].calls += 1

    def _leave(self) -> None:
        self._charge()
        name = self._stack.pop()
        if self._sampling is not None and self._sampling["region"] == name:
            self._stop_sample()

    def _wrap(self, fn, region):
        prof = self

        @functools.wraps(fn)
        def wrapped(*args, **kwargs):
            name = region if region is not None else args[1]  # Fitter._run_phase(self, phase, ...)
            prof._enter(name)
            try:
                return fn(*args, **kwargs)
            finally:
                prof._leave()

        return wrapped

    # -- steps and their samples --------------------------------------------------------------------
    def _step_done(self) -> None:
        name = self._stack[-1]
        r = self.regions[name]
        r.steps += 1
        s = self._sampling
        if s is not None and s["region"] == name:
            s["steps"] += 1
            if s["steps"] >= SAMPLE_STEPS:
                self._stop_sample()
        elif s is None and r.sample is None and r.steps >= SAMPLE_SKIP:
            self._start_sample(name)

    def _start_sample(self, name: str) -> None:
        self._charge()
        acts = [torch.profiler.ProfilerActivity.CPU]
        if self.device.type == "cuda":
            acts.append(torch.profiler.ProfilerActivity.CUDA)
            torch.cuda.synchronize(self.device)
        self._prof = torch.profiler.profile(activities=acts)
        self._prof.__enter__()
        self._sampling = {"region": name, "steps": 0, "kernels": 0.0, "launches": 0, "wp_syncs": 0,
                          "t0": time.perf_counter()}
        self._skip_overhead()  # starting the profiler is not the fit's time
        self._sampling["t0"] = self._t

    def _stop_sample(self) -> None:
        s, prof = self._sampling, self._prof
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        self._charge()
        wall = self._t - s["t0"]
        prof.__exit__(None, None, None)
        self._sampling, self._prof = None, None
        if not s["steps"]:  # cut short before a step ended: the region's next step starts another
            self._skip_overhead()
            return
        n = s["steps"]
        torch_s, sync_s, syncs, ops, device_s = 0.0, 0.0, 0, [], 0.0
        for e in prof.key_averages():
            self_s = e.self_cpu_time_total * 1e-6
            device_s += getattr(e, "self_device_time_total", 0.0) * 1e-6
            if e.key in SYNC_OPS:
                sync_s += self_s
                syncs += e.count
            elif e.key.startswith("aten::"):
                torch_s += self_s
                ops.append((self_s, e.key, e.count))
        ms = 1e3 / n
        sample = {
            "steps": s["steps"],
            "wall_ms_per_step": round(wall * ms, 2),
            "kernels_ms": round(s["kernels"] * ms, 2),
            "torch_ms": round(torch_s * ms, 2),
            "syncs_ms": round(sync_s * ms, 2),
            "python_ms": round((wall - s["kernels"] - torch_s - sync_s) * ms, 2),
            "launches_per_step": round(s["launches"] / n, 1),
            "syncs_per_step": round((syncs + s["wp_syncs"]) / n, 1),
            "top_torch_ops": [{"op": k, "ms_per_step": round(t * ms, 3), "calls_per_step": round(c / n, 1)}
                              for t, k, c in sorted(ops, reverse=True)[:8]],
        }
        if self.device.type == "cuda":
            sample["torch_device_ms"] = round(device_s * ms, 2)
        self.regions[s["region"]].sample = sample
        self._skip_overhead()  # reading the profiler's events is not the fit's time

    def _skip_overhead(self) -> None:
        now = time.perf_counter()
        self._overhead += now - self._t
        self._t = now

    # -- Warp -------------------------------------------------------------------------------------------
    def _timed_warp(self, fn, key_of):
        prof = self

        @functools.wraps(fn)
        def wrapped(*args, **kwargs):
            sync = prof._sampling is not None and prof.device.type == "cuda"
            if sync:
                wp.synchronize_device(str(prof.device))
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                if sync:
                    wp.synchronize_device(str(prof.device))
                dt = time.perf_counter() - t0
                r = prof.regions[prof._stack[-1]]
                r.kernels += dt
                r.launches += 1
                k = prof.kernel_times[key_of(args, kwargs)]
                k[0] += dt
                k[1] += 1
                if prof._sampling is not None:
                    prof._sampling["kernels"] += dt
                    prof._sampling["launches"] += 1

        return wrapped

    def _counted_sync(self, fn):
        prof = self

        @functools.wraps(fn)
        def wrapped(*args, **kwargs):
            if prof._sampling is not None:
                prof._sampling["wp_syncs"] += 1
            return fn(*args, **kwargs)

        return wrapped

    # -- open / close ---------------------------------------------------------------------------------
    def _patch(self, owner, attr, new) -> None:
        self._saved.append((owner, attr, getattr(owner, attr)))
        setattr(owner, attr, new)

    def __enter__(self) -> FitProfile:
        from s3o_warp.fit import Fitter

        for owner, attr, region in _targets():
            self._patch(owner, attr, self._wrap(getattr(owner, attr), region))
        step_window = Fitter.step_window
        prof = self

        @functools.wraps(step_window)
        def counted(*args, **kwargs):
            out = step_window(*args, **kwargs)
            prof._step_done()
            return out

        self._patch(Fitter, "step_window", counted)

        def kernel_name(args, kwargs):
            k = kwargs.get("kernel", args[0] if args else None)
            return getattr(k, "key", str(k))

        self._patch(wp, "launch", self._timed_warp(wp.launch, kernel_name))
        self._patch(wp.Mesh, "__init__", self._timed_warp(wp.Mesh.__init__, lambda a, k: "wp.Mesh (BVH build)"))
        self._patch(wp.Mesh, "refit", self._timed_warp(wp.Mesh.refit, lambda a, k: "wp.Mesh.refit"))
        self._patch(wp, "synchronize_stream", self._counted_sync(wp.synchronize_stream))
        self._t0 = self._t = time.perf_counter()
        return self

    def __exit__(self, *exc) -> bool:
        if self._sampling is not None:
            self._stop_sample()
        self._charge()
        self.wall = time.perf_counter() - self._t0 - self._overhead
        for owner, attr, old in reversed(self._saved):
            setattr(owner, attr, old)
        self._saved.clear()
        return False

    # -- the figures -------------------------------------------------------------------------------
    def report(self) -> dict:
        """``{"wall_s", "phases": [{region, wall_s, share, calls, steps, ms_per_step, kernels_s, launches,
        sample?}], "top_kernels": [...]}``, regions in the order they first ran."""
        phases = []
        for name, r in self.regions.items():
            if r.wall < 1e-4 and not r.steps:
                continue
            row = {"region": name, "wall_s": round(r.wall, 3), "share": round(r.wall / max(self.wall, 1e-9), 4),
                   "calls": r.calls, "steps": r.steps, "kernels_s": round(r.kernels, 3), "launches": r.launches}
            if r.steps:
                row["ms_per_step"] = round(1e3 * r.wall / r.steps, 2)
            if r.sample is not None:
                row["sample"] = r.sample
            phases.append(row)
        top = sorted(self.kernel_times.items(), key=lambda kv: -kv[1][0])[:12]
        return {"wall_s": round(self.wall, 3), "phases": phases,
                "top_kernels": [{"kernel": k, "seconds": round(t, 3), "launches": n} for k, (t, n) in top]}

