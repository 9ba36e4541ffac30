"""Branched fits (run/branch.py) and the checkpoints they start from (run/checkpoint.py)."""

from __future__ import annotations

import json

import pytest
import torch
from conftest import final_params, smoke_config

from s3o_warp.errors import InputError
from s3o_warp.fit import Fitter, fit
from s3o_warp.run.checkpoint import CHECKPOINT_VERSION, latest_checkpoint

_cfg = smoke_config  # tiny_sequence: conftest.py


def test_a_fit_branched_at_another_t_o_ends_where_a_fresh_fit_at_it_ends(tiny_sequence, tmp_path, monkeypatch):
    """``fit(..., branch_from=run)``: a fit at another t_o started from ``run``'s branch checkpoint (the state just
    before its first merge, that M-step pending) gives the parameters of a fresh fit at that t_o, runs only the
    steps after the branch, and its log counts on from the branch."""
    over = {"coarse.steps": 4, "motion.warmup_steps": 4, "motion.steps": 10, "skeleton.epochs": 5, "skeleton.e1": 1,
            "motion.log_every": 1}
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    calls = {"n": 0}
    orig = Fitter.motion_losses

    def counting(self, frames):
        calls["n"] += 1
        return orig(self, frames)

    monkeypatch.setattr(Fitter, "motion_losses", counting)
    fit(tiny_sequence, a, _cfg(**over, **{"skeleton.t_o": 0.999}), torch.device("cpu"))
    assert (a / "checkpoints" / "branch.pt").is_file()
    calls["n"] = 0
    fit(tiny_sequence, b, _cfg(**over, **{"skeleton.t_o": -1.0}), torch.device("cpu"))
    fresh = calls["n"]
    pa, pb = final_params(a), final_params(b)
    assert any(pa[k].shape != pb[k].shape or not torch.equal(pa[k], pb[k]) for k in pa)  # t_o acts after the branch
    calls["n"] = 0
    fit(tiny_sequence, c, _cfg(**over, **{"skeleton.t_o": -1.0}), torch.device("cpu"), branch_from=a)
    # 10 joint steps in 5 epochs of 2: the first merge follows epoch e1 + 1 = 2, at joint step 6; 4 steps remain
    assert calls["n"] == 4 < fresh
    pc = final_params(c)
    for k in pb:
        torch.testing.assert_close(pc[k], pb[k], rtol=0, atol=1e-6, msg=f"branched fit differs in {k}")
    rows = [json.loads(line) for line in open(c / "log.jsonl")]
    joint = [r["step"] for r in rows if r["phase"] == "joint" and "lr" in r]
    assert joint == list(range(1, 11)) and rows[0]["phase"] == "eval"  # a's log up to the branch, then c's own
    secs = [r["seconds"] for r in rows]
    assert secs == sorted(secs)
    assert json.loads((c / "skeleton.json").read_text())["bones"] == json.loads((b / "skeleton.json").read_text())["bones"]
    # joint creation's t_d and the halves test's t_u are read only after the branch too
    other = {**over, "skeleton.t_o": 0.5, "skeleton.t_d": 0.05, "skeleton.t_u": 0.3}
    fit(tiny_sequence, tmp_path / "d", _cfg(**other), torch.device("cpu"))
    fit(tiny_sequence, tmp_path / "e", _cfg(**other), torch.device("cpu"), branch_from=a)
    pd, pe = final_params(tmp_path / "d"), final_params(tmp_path / "e")
    for k in pd:
        torch.testing.assert_close(pe[k], pd[k], rtol=0, atol=1e-6, msg=f"branched fit with those settings differs in {k}")


def test_a_branch_refuses_other_settings_and_a_run_without_its_checkpoint(tiny_sequence, tmp_path):
    over = {"coarse.steps": 2, "motion.warmup_steps": 2, "motion.steps": 8, "skeleton.epochs": 4, "skeleton.e1": 1}
    a = tmp_path / "a"
    fit(tiny_sequence, a, _cfg(**over), torch.device("cpu"))
    with pytest.raises(InputError, match=r"differ in motion.lr_bones .*only skeleton.t_o, skeleton.t_u, skeleton.t_d may differ"):
        fit(tiny_sequence, tmp_path / "b", _cfg(**over, **{"motion.lr_bones": 0.123}), torch.device("cpu"), branch_from=a)
    assert not (tmp_path / "b").exists()  # refused before any work
    # a setting the parent's run lacks is a difference, not read at today's default
    from s3o_warp.run.branch import branch_checkpoint as _branch_checkpoint

    ck = a / "checkpoints" / "branch.pt"
    state = torch.load(ck, map_location="cpu", weights_only=False)
    assert _branch_checkpoint(a, tmp_path / "e", _cfg(**over)) == ck
    del state["config"]["motion"]["resample_epochs"]
    torch.save(state, ck)
    with pytest.raises(InputError, match=r"differ in motion.resample_epochs \(None there, 1 here\)"):
        _branch_checkpoint(a, tmp_path / "e", _cfg(**over))
    # a parent written by an earlier version of the checkpoints is refused in one line: refit it
    state["version"] = CHECKPOINT_VERSION - 1
    torch.save(state, ck)
    with pytest.raises(InputError, match=r"^--branch-from .*checkpoints/branch.pt was written by an earlier version "
                                         r"of s3o-warp .* and must be refit: refit that run, then branch from it$"):
        fit(tiny_sequence, tmp_path / "f", _cfg(**over), torch.device("cpu"), branch_from=a)
    assert not (tmp_path / "f").exists()
    with pytest.raises(InputError, match="that is the run directory itself"):
        fit(tiny_sequence, a, _cfg(**over), torch.device("cpu"), branch_from=a)
    short = tmp_path / "short"  # 3 epochs, e1 1: the last M-step is the upsampling, t_o is never read
    fit(tiny_sequence, short, _cfg(**{**over, "skeleton.epochs": 3}), torch.device("cpu"))
    assert not (short / "checkpoints" / "branch.pt").exists()
    with pytest.raises(InputError, match=r"no checkpoints/branch.pt there"):
        fit(tiny_sequence, tmp_path / "d", _cfg(**{**over, "skeleton.epochs": 3}), torch.device("cpu"), branch_from=short)


def test_resume_refuses_a_checkpoint_of_another_sequence(tiny_sequence, tmp_path):
    from s3o_warp.synth import make_sequence

    cfg = _cfg(**{"coarse.steps": 2, "motion.warmup_steps": 2, "motion.steps": 2})
    run = tmp_path / "run"
    fit(tiny_sequence, run, cfg, torch.device("cpu"))
    other = make_sequence(tmp_path / "other", frames=6, size=(96, 72), seed=1, progress=False)
    with pytest.raises(InputError, match="belongs to sequence"):
        fit(other, run, cfg, torch.device("cpu"), resume=True)
    # the other principal-point model: its parameters do not fit this one's, refused with the setting to pass
    pp = cfg.motion.principal_point
    other_pp = {"frame": "shared", "shared": "frame"}[pp]
    with pytest.raises(InputError, match=f"written with motion.principal_point={pp}.*--set motion.principal_point={pp}"):
        fit(tiny_sequence, run, _cfg(**{"coarse.steps": 2, "motion.warmup_steps": 2, "motion.steps": 2,
                                        "motion.principal_point": other_pp}), torch.device("cpu"), resume=True)
    # a checkpoint written by another version of the format is refused with the reason
    ck = latest_checkpoint(run)
    st = torch.load(ck, weights_only=False)
    st["version"] = 999
    torch.save(st, ck)
    with pytest.raises(InputError, match="another version of s3o-warp \\(checkpoint version 999"):
        fit(tiny_sequence, run, cfg, torch.device("cpu"), resume=True)
    st["version"] = CHECKPOINT_VERSION - 1
    torch.save(st, ck)
    with pytest.raises(InputError, match="written by an earlier version of s3o-warp .* must be refit"):
        fit(tiny_sequence, run, cfg, torch.device("cpu"), resume=True)
