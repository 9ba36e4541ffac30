"""The camera hypotheses at the start of the warm-up (motion/hypotheses.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from conftest import smoke_config

from s3o_warp.coarse.model import coarse_model
from s3o_warp.data.store import prepare_data
from s3o_warp.fit import Fitter, fit
from s3o_warp.run.checkpoint import latest_checkpoint

_cfg = smoke_config  # tiny_sequence: conftest.py


@pytest.mark.parametrize("refine", [0, 2])
def test_camera_hypotheses_score_each_rate_and_keep_the_best(tiny_sequence, tmp_path, refine, monkeypatch):
    import s3o_warp.motion.hypotheses as H
    from s3o_warp.geometry import axis_angle_to_matrix

    monkeypatch.setattr(H, "HYPOTHESIS_REFINE", refine)
    monkeypatch.setattr(H, "HYPOTHESIS_REFINE_STEPS", 2)
    cfg = _cfg(**{"coarse.steps": 2, "motion.warmup_steps": 2, "motion.steps": 2,
                  "motion.hypotheses": 3, "motion.hypothesis_steps": 2})
    run = tmp_path / "run"
    fit(tiny_sequence, run, cfg, torch.device("cpu"))
    rec = next(json.loads(l) for l in (run / "log.jsonl").read_text().splitlines() if '"hypotheses"' in l)
    r = cfg.motion.hypothesis_max_rate
    assert len(rec["scores"]) == 3 and rec["rates_deg_per_frame"] == [-r, 0.0, r]
    if refine:  # the best two of the first round are refined and the best refined one is chosen
        top2 = sorted(np.argsort(rec["scores"])[:2])
        assert sorted(float(k) for k in rec["refined"]) == [rec["rates_deg_per_frame"][i] for i in top2]
        assert rec["chosen"] == float(min(rec["refined"], key=rec["refined"].get))
    else:
        assert rec["refined"] == {} and rec["chosen"] == rec["rates_deg_per_frame"][int(np.argmin(rec["scores"]))]
    # the chosen turn is what the model's base root rotation holds
    st = torch.load(latest_checkpoint(run), weights_only=False)["model"]
    R0 = st["root_R0"]
    T = R0.shape[0]
    rel = R0[0].T @ R0[-1]
    aa = torch.zeros(1, 3)
    aa[0, 1] = np.deg2rad(rec["chosen"] * (T - 1))
    torch.testing.assert_close(rel, axis_angle_to_matrix(aa)[0], atol=1e-5, rtol=0)


def test_hypotheses_are_scored_on_every_frame(tiny_sequence, tmp_path, monkeypatch):
    """The all-frames score sees every frame and every flow pair (t, t+1) once the steps are done."""
    cfg = _cfg(**{"coarse.steps": 2, "motion.batch_frames": 3})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    seen, orig = [], Fitter.motion_losses

    def record(self, frames):
        seen.append(frames.tolist())
        return orig(self, frames)

    monkeypatch.setattr(Fitter, "motion_losses", record)
    terms = f.mean_terms()
    T = data.num_frames
    assert sorted({t for w in seen for t in w}) == list(range(T))
    pairs = {(w[i], w[i + 1]) for w in seen for i in range(len(w) - 1)}
    assert pairs == {(t, t + 1) for t in range(T - 1)}
    assert all(w == list(range(w[0], w[0] + 3)) for w in seen)
    # each term is the mean over those windows of weight x value
    windows = [torch.tensor(w) for w in seen]
    for k in ("sil", "flow"):
        with torch.no_grad():
            want = np.mean([float(w * v) for w, v in (orig(f, fr)[0][k] for fr in windows)])
        assert terms[k] == pytest.approx(want, rel=1e-6)


def test_hypotheses_are_ranked_by_their_flow_term_or_else_the_whole_loss(tiny_sequence, tmp_path, monkeypatch):
    """The optical-flow term over every frame ranks the hypotheses; a sequence without a flow term (faked here)
    ranks them by the sum of its terms."""
    import s3o_warp.motion.hypotheses as H

    monkeypatch.setattr(H, "HYPOTHESIS_REFINE", 0)
    cfg = _cfg(**{"coarse.steps": 2, "motion.hypotheses": 3, "motion.hypothesis_steps": 1})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    scored = iter([{"flow": 0.3, "sil": 0.0}, {"flow": 0.1, "sil": 5.0}, {"flow": 0.2, "sil": 0.0},
                   {"sil": 0.3, "smooth": 0.1}, {"sil": 0.1, "smooth": 0.4}, {"sil": 0.2, "smooth": 0.0}])
    monkeypatch.setattr(Fitter, "mean_terms", lambda self: next(scored))
    assert H.select_hypothesis(f) == 0.0  # rates -3, 0, 3: the lowest flow term, not the lowest total
    assert H.select_hypothesis(f) == 3.0  # no flow term: the lowest total


def test_known_turn_rate_skips_the_scoring(tiny_sequence, tmp_path):
    cfg = _cfg(**{"coarse.steps": 2, "motion.warmup_steps": 2, "motion.steps": 2, "motion.turn_rate": 1.5})
    run = tmp_path / "run"
    fit(tiny_sequence, run, cfg, torch.device("cpu"))
    rec = next(json.loads(l) for l in (run / "log.jsonl").read_text().splitlines() if '"hypotheses"' in l)
    assert rec["rates_deg_per_frame"] == [1.5] and rec["chosen"] == 1.5


def test_a_signal_during_the_hypotheses_stops_within_2_s_and_resume_ends_where_an_uninterrupted_fit_ends(
        tiny_sequence, tmp_path, monkeypatch, sigint_raises):
    """SIGINT once the search has begun (seen through its progress bar and its scoring): the fit stops with a
    checkpoint holding the search, in the first round's steps, then (resumed) in a rate's scoring, then in the
    second round. Resumed each time, the fit chooses the same turn and ends with the same parameters as an
    uninterrupted fit of the same seed."""
    import os
    import signal
    import time

    import s3o_warp.motion.hypotheses as H
    from conftest import final_params

    from s3o_warp.fit import FitInterrupted

    monkeypatch.setattr(H, "HYPOTHESIS_REFINE", 2)
    monkeypatch.setattr(H, "HYPOTHESIS_REFINE_STEPS", 3)
    cfg = _cfg(**{"coarse.steps": 2, "motion.warmup_steps": 2, "motion.steps": 2,
                  "motion.hypotheses": 3, "motion.hypothesis_steps": 3})
    a, b = tmp_path / "a", tmp_path / "b"
    fit(tiny_sequence, a, cfg, torch.device("cpu"))

    sent = []  # when each SIGINT was sent

    def send():
        sent.append(time.perf_counter())
        os.kill(os.getpid(), signal.SIGINT)

    class Hooked(H.tqdm):  # steps of the search: 3 rates x 3 steps, then 2 finalists x 3 steps
        def update(self, n=1):
            super().update(n)
            if self.n in (5, 11) and len(sent) == (0 if self.n == 5 else 2):
                send()

    orig, scored = Fitter.mean_terms, []

    def scoring(self):
        scored.append(1)
        if len(scored) == 2:  # the second rate's score, in the first resumed fit
            send()
        return orig(self)

    monkeypatch.setattr(H, "tqdm", Hooked)
    monkeypatch.setattr(Fitter, "mean_terms", scoring)
    stops = (("turn rate 2 of 3, step 2", 2), ("turn rate 2 of 3, step 3", 3), ("finalist 1 of 2, step 2", 2))
    for k, (where, done) in enumerate(stops):
        with pytest.raises(FitInterrupted, match=f"camera hypotheses \\({where}\\)"):
            fit(tiny_sequence, b, cfg, torch.device("cpu"), resume=k > 0)
        assert time.perf_counter() - sent[k] < 2.0
        st = torch.load(latest_checkpoint(b), weights_only=False)
        assert (st["phase"], st["step"], st["hypotheses"]["steps_done"]) == ("warmup", 0, done)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handlers are back (sigint_raises')
    fit(tiny_sequence, b, cfg, torch.device("cpu"), resume=True)

    def chosen(run):
        rec = [json.loads(l) for l in (run / "log.jsonl").read_text().splitlines() if '"hypotheses"' in l]
        return [{k: r[k] for k in ("scores", "refined", "chosen")} for r in rec]

    assert chosen(b) == chosen(a) and len(chosen(a)) == 1
    pa, pb = final_params(a), final_params(b)
    assert pa.keys() == pb.keys()
    for k in pa:
        torch.testing.assert_close(pb[k], pa[k], rtol=0, atol=0, msg=f"resumed fit differs in {k}")
