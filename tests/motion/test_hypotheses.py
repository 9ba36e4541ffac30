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


def test_flow_by_gap_scores_every_pair_of_every_gap_against_a_dense_twin(tiny_sequence, tmp_path):
    """flow_by_gap's error at each gap equals the flow loss of every pair (t, t + g) computed directly (frame t
    rendered, both posed); an observed flow equal to the model's own displacement scores 0, and a turn added to
    the later frames scores more at the longer gaps."""
    from s3o_warp.geometry import axis_angle_to_matrix, project
    from s3o_warp.kernels.raster import rasterize
    from s3o_warp.motion import losses as L
    from s3o_warp.motion.objective import flow_by_gap
    from s3o_warp.ops import interpolate

    cfg = _cfg(**{"coarse.steps": 2, "motion.batch_frames": 3, "motion.hypotheses": 3})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    assert sorted(data.long_flow) == [2, 4]  # 8 frames: gaps 1, 2, 4
    off = _cfg(**{"coarse.steps": 2, "motion.hypotheses": 3, "motion.turn_rate": 1.0})
    assert prepare_data(tiny_sequence, off, tmp_path, torch.device("cpu")).long_flow == {}  # no scoring: gap 1 only
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    m, S, T = f.model, data.crop_size, data.num_frames
    got = f.flow_by_gap()
    assert sorted(got) == [1, 2, 4]

    def twin(g, flow, conf):
        num = den = 0.0
        with torch.no_grad():
            for t in range(T - g):
                a, b = torch.tensor([t]), torch.tensor([t + g])
                fi, bary, _ = rasterize(m(a), m.faces, m.intrinsics_crop(a), (S, S))
                disp = project(m(b), m.intrinsics_crop(b)) - project(m(a), m.intrinsics_crop(a))
                r = interpolate(disp, m.faces, fi, bary)
                w = conf[t:t + 1] * (fi >= 0).float() * data.masks[a]
                num += float((w * (r - flow[t:t + 1]).norm(dim=-1)).sum())
                den += float(w.sum())
        return num / max(den, 1.0)

    stores = {1: (data.flow_fwd, data.conf_fwd), **data.long_flow}
    for g, (flow, conf) in stores.items():
        fl = flow[torch.arange(T - g)]
        cf = conf[torch.arange(T - g)]
        assert got[g] == pytest.approx(twin(g, fl, cf), rel=1e-5)
    # the model's own displacement as the observed flow scores 0 at every gap
    own = {}
    for g in (1, 2, 4):
        rows = []
        for t in range(T - g):
            a, b = torch.tensor([t]), torch.tensor([t + g])
            with torch.no_grad():
                fi, bary, _ = rasterize(m(a), m.faces, m.intrinsics_crop(a), (S, S))
                disp = project(m(b), m.intrinsics_crop(b)) - project(m(a), m.intrinsics_crop(a))
                rows.append(interpolate(disp, m.faces, fi, bary)[0])
        own[g] = torch.stack(rows)
    data.flow_fwd, data.conf_fwd = own[1], torch.ones(T - 1, S, S)
    data.long_flow = {g: (own[g], torch.ones(T - g, S, S)) for g in (2, 4)}
    assert max(f.flow_by_gap().values()) < 1e-4
    with torch.no_grad():  # 2 degrees a frame more turn: the error grows with the gap
        aa = torch.zeros(T, 3)
        aa[:, 1] = torch.deg2rad(torch.tensor(2.0)) * torch.arange(T)
        m.root_R0.copy_(m.root_R0 @ axis_angle_to_matrix(aa))
    turned = f.flow_by_gap()
    assert 0.05 < turned[1] < turned[2] < turned[4]


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


def test_hypotheses_are_ranked_by_their_flow_error_over_the_gaps_or_else_the_whole_loss(tiny_sequence, tmp_path,
                                                                                       monkeypatch):
    """The mean over the gaps of the flow error ranks the hypotheses; a sequence without a flow term
    (``motion.w_flow=0``) ranks them by the sum of its terms."""
    import s3o_warp.motion.hypotheses as H

    monkeypatch.setattr(H, "HYPOTHESIS_REFINE", 0)
    cfg = _cfg(**{"coarse.steps": 2, "motion.hypotheses": 3, "motion.hypothesis_steps": 1})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    by_gap = iter([{1: 0.1, 2: 0.9}, {1: 0.3, 2: 0.3}, {1: 0.2, 2: 0.5}])
    monkeypatch.setattr(Fitter, "flow_by_gap", lambda self: next(by_gap))
    monkeypatch.setattr(Fitter, "mean_terms", lambda self: pytest.fail("scored by the whole loss"))
    assert H.select_hypothesis(f) == 0.0  # rates -3, 0, 3: the lowest mean over the gaps, not the lowest at gap 1
    f.cfg.motion.w_flow = 0.0
    scored = iter([{"sil": 0.3, "smooth": 0.1}, {"sil": 0.1, "smooth": 0.4}, {"sil": 0.2, "smooth": 0.0}])
    monkeypatch.setattr(Fitter, "mean_terms", lambda self: next(scored))
    assert H.select_hypothesis(f) == 3.0  # no flow term: the lowest total


def test_the_chosen_rate_is_the_vertex_of_the_v_the_refined_scores_form():
    from s3o_warp.motion.hypotheses import v_minimum

    def v(r):
        return 4.0 + 3.0 * abs(r - 2.6)

    assert v_minimum([2.0, 3.0, 1.0], [v(2.0), v(3.0), v(1.0)], 3.0) == pytest.approx(2.6)
    assert v_minimum([3.0, 1.0, 2.0], [v(3.0), v(1.0), v(2.0)], 3.0) == pytest.approx(2.6)  # any order
    assert v_minimum([0.0, 1.0, 2.0], [3.0, 2.0, 1.0], 2.0) == 2.0  # still falling at the edge: the edge
    assert v_minimum([0.0, 1.0, 2.0], [1.0, 1.0, 1.0], 1.0) == 1.0  # no V: the fallback
    assert v_minimum([0.0, 1.0], [1.0, 0.0], 1.0) == 1.0  # two rates do not make a V


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

    orig, scored = Fitter.flow_by_gap, []

    def scoring(self):
        scored.append(1)
        if len(scored) == 2:  # the second rate's score, in the first resumed fit
            send()
        return orig(self)

    monkeypatch.setattr(H, "tqdm", Hooked)
    monkeypatch.setattr(Fitter, "flow_by_gap", scoring)
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
