"""The fit profile (s3o_warp/run/profile.py): regions add up to the fit, steps are counted, nothing stays wrapped."""

from __future__ import annotations

import pytest
import torch
import warp as wp
from conftest import smoke_config

from s3o_warp.fit import Fitter, fit
from s3o_warp.run import profile as P


def test_a_profiled_fit_splits_its_time_by_phase_and_step_and_leaves_nothing_wrapped(tiny_sequence, tmp_path,
                                                                                     monkeypatch):
    monkeypatch.setattr(P, "SAMPLE_STEPS", 3)
    cfg = smoke_config(**{"coarse.steps": 6, "motion.warmup_steps": 6, "motion.steps": 12, "skeleton.epochs": 2})
    launch, step_window = wp.launch, Fitter.step_window
    with P.FitProfile("cpu") as prof:
        fit(tiny_sequence, tmp_path / "run", cfg, torch.device("cpu"))
    assert wp.launch is launch and Fitter.step_window is step_window  # closed: a fit pays nothing
    r = prof.report()
    rows = {p["region"]: p for p in r["phases"]}
    assert {"flow", "lift", "coarse", "warmup", "joint", "m-step", "resample", "metrics"} <= rows.keys()
    assert [rows[k]["steps"] for k in ("coarse", "warmup", "joint")] == [6, 6, 12]
    # each stretch of time is charged once: the regions add up to the fit
    assert sum(p["wall_s"] for p in r["phases"]) == pytest.approx(r["wall_s"], rel=1e-3)
    assert sum(p["share"] for p in r["phases"]) == pytest.approx(1.0, abs=1e-2)
    for k in ("coarse", "warmup", "joint"):
        row, s = rows[k], rows[k]["sample"]
        assert 0 < row["kernels_s"] < row["wall_s"] and row["launches"] > 0
        assert s["steps"] == 3 and s["launches_per_step"] > 0
        parts = s["kernels_ms"] + s["torch_ms"] + s["syncs_ms"] + s["python_ms"]
        assert parts == pytest.approx(s["wall_ms_per_step"], abs=0.05)
        assert s["kernels_ms"] > 0 and s["torch_ms"] > 0 and s["top_torch_ops"]
    launches = sum(p["launches"] for p in r["phases"])
    assert sum(k["launches"] for k in r["top_kernels"]) <= launches
    assert r["top_kernels"][0]["seconds"] > 0
