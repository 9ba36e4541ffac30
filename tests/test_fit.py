"""End-to-end fit on a tiny built-in quadruped clip: it must reconstruct, resume exactly and repeat."""

from __future__ import annotations

import copy
import json
import logging
from unittest import mock

import numpy as np
import pytest
import torch
from conftest import smoke_config

from s3o_warp.data import flow as video_flow
from s3o_warp.config import make_config
from s3o_warp.errors import ConfigError, InputError
from s3o_warp.coarse.model import coarse_model
from s3o_warp.data.store import prepare_data
from s3o_warp.fit import FitInterrupted, Fitter, fit, resolve_device
from s3o_warp.motion.windows import seed_unvisited
from s3o_warp.run.checkpoint import CHECKPOINT_VERSION, latest_checkpoint

_cfg = smoke_config  # tiny_sequence: conftest.py


def test_coarse_phase_builds_a_quadruped_skeleton(tiny_sequence, tmp_path):
    cfg = _cfg()
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    res = coarse_model(data, cfg)
    # a side view of the built-in quadruped: a tree of bones with a torso root and limbs hanging off it
    parents = res.parents
    assert (parents == -1).sum() == 1
    assert len(parents) >= 5
    v = res.init.verts.numpy()
    assert np.isfinite(v).all() and len(v) > 100
    # the coarse mesh, posed by the canonical root, projects onto the canonical crop's mask
    from s3o_warp.model import S3OModel

    m = S3OModel(res.init)
    c = torch.tensor([res.canonical])
    with torch.no_grad():
        from s3o_warp.kernels.raster import rasterize

        fi, _, _ = rasterize(m(c), m.faces, m.intrinsics_crop(c), (64, 64))
    pred = (fi[0] >= 0).numpy()
    gt = data.masks[res.canonical].numpy() > 0.5
    iou = (pred & gt).sum() / (pred | gt).sum()
    assert iou > 0.5, iou


def test_small_fit_raises_iou_and_writes_the_run_directory(tiny_sequence, tmp_path):
    cfg = _cfg(**{"coarse.steps": 30, "motion.warmup_steps": 40, "motion.steps": 60})
    run = tmp_path / "run"
    metrics = fit(tiny_sequence, run, cfg, torch.device("cpu"))
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    evals = {r["what"]: r["iou_all_frames"] for r in log if r["phase"] == "eval" and "iou_all_frames" in r}
    assert any(r.get("what") == "resample" for r in log)  # even resampling ran at the epoch ends
    # hard-render IoU over all frames: the coarse model at the start against the end of the fit
    assert evals["final"] > evals["initial"] + 0.1, evals
    for name in ("config.toml", "canonical.ply", "skeleton.json", "motion.npz", "metrics.json", "quad.usdc", "quad.glb"):
        assert (run / name).is_file(), name
    assert metrics["mask_iou"]["mean"] > 0.6
    assert metrics["pck_t"]["pck"] is not None
    _check_exported_fit(run, "quad")


def test_fit_of_a_small_clip_learns_the_quadrupeds_skeleton(small_sequence, tmp_path):
    """Four legs, a tail, a neck and a head (see :func:`_check_skeleton_shape` for the tolerances)."""
    cfg = _cfg(**{"data.crop_size": 96, "coarse.target_vertices": 1200, "coarse.steps": 30,
                  "motion.warmup_steps": 40, "motion.steps": 60})
    run = tmp_path / "run"
    metrics = fit(small_sequence, run, cfg, torch.device("cpu"))
    _check_skeleton_shape(run, small_sequence, metrics)


@pytest.mark.parametrize("method", ["s3o", "virtual"])
def test_bones_refit_to_their_coarse_parts_only_for_the_lift(tiny_sequence, tmp_path, method):
    """After the coarse fit the lift's bones move onto their labelled parts; the virtual baseline's k-means
    bones have no parts and stay where k-means put them, and its short fit runs through."""
    from s3o_warp.coarse.model import REFIT_MIN_FACES, refit_bones_to_parts
    from s3o_warp.skeleton.edit import fit_bones_to_parts

    cfg = _cfg(**{"coarse.steps": 4, "motion.warmup_steps": 4, "motion.steps": 4, "skeleton.method": method,
                  "skeleton.virtual_bones": 6})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    res = coarse_model(data, cfg)
    (tmp_path / "run").mkdir()
    fitter = Fitter(data, res, cfg, tmp_path / "run", torch.device("cpu"))
    m = fitter.model
    C0, Q0 = m.bone_centers.detach().clone(), m.precisions().detach().clone()
    if method == "s3o":  # the loop refits only the lift's bones
        refit_bones_to_parts(m, res)
    if method == "virtual":
        assert C0.shape[0] == 6
        torch.testing.assert_close(m.bone_centers, C0, rtol=0, atol=0)
        torch.testing.assert_close(m.precisions(), Q0, rtol=0, atol=0)
        fitter.run()
        assert (fitter.skel.parents == np.r_[-1, np.zeros(5, int)]).all()
        return
    C, Q, moved = fit_bones_to_parts(m.verts.detach(), m.faces, res.face_parts, C0, Q0, REFIT_MIN_FACES)
    assert moved.sum() >= len(moved) // 2 and np.abs(C - C0.numpy()).max() > 1e-3
    np.testing.assert_allclose(m.bone_centers.detach().numpy(), C, atol=1e-6)
    np.testing.assert_allclose(m.precisions().detach().numpy(), Q, rtol=1e-4, atol=1e-3 * np.abs(Q).max())


def _check_skeleton_shape(run, sequence, metrics):
    """The learned skeleton has the quadruped's shape: a joint along each of the four legs, the tail and the
    neck, and one at the head, all inside the body.

    Tolerance: after the run's similarity alignment, in at least half of the frames, a learned joint lies
    within 8 % of the bounding-box diagonal of each leg's own chain (shoulder or hip -> knee -> foot) and of the
    tail's own chain (base -> tip), within 8 % of the neck (withers -> neck -> head) and within 10 % of the
    head; the chains leave out the joint where the limb meets the body (``branch=False``), so a hip joint does
    not count for the tail (the head: head -> nose). At least 85 % of the (frame, joint) pairs are inside the
    posed mesh.

    Measured on ``small_sequence`` (clip seed 0) with this test's settings: legs 3.9-5.1 %, tail 2.4 %, neck
    3.8 %, head 4.1 %, joints inside 0.97, 19 bones. The bounds are not met on every clip of this size: on clip
    seeds 1-3 (``make_sequence(..., seed=s)``) the legs need 3.6-6.2, 3.8-5.5 and 3.8-8.2 %, the tail 9.1, 3.0
    and 4.4 %, so clip 1 loses its tail (the tail bone's vertices go to the body during the joint phase) and
    clip 3's front-left leg misses by 0.2 points. At ``tiny_sequence``'s size (64 px crops, 300 coarse
    vertices) the coarse mesh has no tail at all: it is 1-2 px thick there.
    """
    from s3o_warp.evaluation import metrics as M

    pred, gt = M.load_predictions(run), M.load_ground_truth(sequence / "ground_truth")
    a = metrics["shape_3d"]["alignment"]
    sim = M.Similarity(a["scale"], np.array(a["rotation"]), np.array(a["translation"]))
    diag = M.bbox_diagonal(gt.verts)
    names = list(gt.joint_names)
    cov = M.limb_coverage(pred.joints_cam, gt.joints, gt.joint_parents, diag, sim, names, min_joints=1,
                          branch=False)
    need = {limb["limb"]: limb["tol_needed"] for limb in cov["limbs"]}
    head = [names.index(n) for n in ("head", "nose")]
    need["nose"] = M.chain_coverage(pred.joints_cam, gt.joints, head, diag, sim, min_joints=1)["tol_needed"]
    neck = [names.index(n) for n in ("withers", "neck", "head")]
    need["neck"] = M.chain_coverage(pred.joints_cam, gt.joints, neck, diag, sim, min_joints=1)["tol_needed"]
    bounds = {"foot_fl": 0.08, "foot_fr": 0.08, "foot_bl": 0.08, "foot_br": 0.08, "tail_tip": 0.08, "neck": 0.08,
              "nose": 0.10}
    assert all(need[k] < b for k, b in bounds.items()), need
    parents = np.array([b["parent"] for b in json.loads((run / "skeleton.json").read_text())["bones"]])
    assert (parents == -1).sum() == 1
    assert metrics["joints_inside"]["fraction"] >= 0.85, metrics["joints_inside"]


def _check_exported_fit(run, name):
    """The export of a real fit: UsdSkel's skinning (top-K weights) and Gf.Camera reproduce the rig."""
    from pxr import Usd
    from test_export import gf_camera_project, usd_skinned_world, validation_errors

    from s3o_warp.export.rig import dense_weights, load_rig, top_k_weights
    from s3o_warp.export.usd import export_usd

    rig = load_rig(run)
    B = rig.num_bones
    report = export_usd(rig, run / f"{name}_all.usda", influences=B)  # all influences: exact
    stage = Usd.Stage.Open(str(report.path))
    tol = 1e-4 * rig.bbox_diagonal()
    proj = rig.project()
    for t in (0, rig.num_frames - 1):
        world = usd_skinned_world(stage, t)
        np.testing.assert_allclose(world, rig.posed_world(t), atol=tol, rtol=0)
        assert np.abs(gf_camera_project(stage, t, world, rig.image_size) - proj[t]).max() < 0.5
    assert validation_errors(stage) == []
    # the default file (4 influences) is exact for the pruned weights
    stage4 = Usd.Stage.Open(str(run / f"{name}.usdc"))
    idx, val = top_k_weights(rig.weights, 4)
    dense = dense_weights(idx, val, B)
    np.testing.assert_allclose(usd_skinned_world(stage4, 1), rig.posed_world(1, weights=dense), atol=tol, rtol=0)


def _final_params(run):
    st = torch.load(latest_checkpoint(run), weights_only=False)
    return st["model"]


def _interrupt_resume_and_compare(seq, a, b, cfg, monkeypatch, interrupting, where: str) -> None:
    """Fit into ``b`` with ``interrupting`` as the motion losses (it asks for a stop), resume, and compare the final
    parameters with the uninterrupted fit in ``a``; ``where``: what the interrupt's message names."""
    orig = Fitter.motion_losses
    monkeypatch.setattr(Fitter, "motion_losses", interrupting)
    with pytest.raises(FitInterrupted, match=where):
        fit(seq, b, cfg, torch.device("cpu"))
    monkeypatch.setattr(Fitter, "motion_losses", orig)
    fit(seq, b, cfg, torch.device("cpu"), resume=True)
    pa, pb = _final_params(a), _final_params(b)
    for k in pa:
        torch.testing.assert_close(pb[k], pa[k], rtol=0, atol=1e-6, msg=f"resume ({where}) differs in {k}")


def test_resume_after_interrupt_matches_uninterrupted(tiny_sequence, tmp_path, monkeypatch):
    cfg = _cfg(**{"coarse.steps": 6, "motion.warmup_steps": 6, "motion.steps": 8})
    a, b = tmp_path / "a", tmp_path / "b"
    fit(tiny_sequence, a, cfg, torch.device("cpu"))

    orig = Fitter.motion_losses
    calls = {"n": 0}

    def interrupting(self, frames):
        calls["n"] += 1
        if calls["n"] == 9:  # mid joint phase (6 warm-up steps + 3)
            self.request_stop()
        return orig(self, frames)

    _interrupt_resume_and_compare(tiny_sequence, a, b, cfg, monkeypatch, interrupting, "stopped at joint step")


def test_same_seed_repeats_bit_for_bit_on_threads(tiny_sequence, tmp_path):
    """Two fits of one seed give the same parameters (``repeatable``); torch's setting is the caller's after.

    Measured with ``repeatable=false`` (2 threads): this 40-step fit at 96 px crops parts from its rerun in
    every parameter (bone counts too) in 3 of 3 pairs; the threaded backward of indexing adds in thread order.
    """
    cfg = _cfg(**{"coarse.steps": 6, "motion.warmup_steps": 20, "motion.steps": 20, "data.crop_size": 96})
    threads = torch.get_num_threads()
    torch.set_num_threads(max(2, threads))  # the race needs two threads
    try:
        fit(tiny_sequence, tmp_path / "a", cfg, torch.device("cpu"))
        fit(tiny_sequence, tmp_path / "b", cfg, torch.device("cpu"))
    finally:
        torch.set_num_threads(threads)
    assert not torch.are_deterministic_algorithms_enabled()
    pa, pb = _final_params(tmp_path / "a"), _final_params(tmp_path / "b")
    assert pa.keys() == pb.keys()
    differ = [k for k in pa if pa[k].shape != pb[k].shape or not torch.equal(pa[k], pb[k])]
    assert not differ, f"same seed, different {differ}"


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
    pa, pb = _final_params(a), _final_params(b)
    assert any(pa[k].shape != pb[k].shape or not torch.equal(pa[k], pb[k]) for k in pa)  # t_o acts after the branch
    calls["n"] = 0
    fit(tiny_sequence, c, _cfg(**over, **{"skeleton.t_o": -1.0}), torch.device("cpu"), branch_from=a)
    # 10 joint steps in 5 epochs of 2: the first merge follows epoch e1 + 1 = 2, at joint step 6; 4 steps remain
    assert calls["n"] == 4 < fresh
    pc = _final_params(c)
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
    pd, pe = _final_params(tmp_path / "d"), _final_params(tmp_path / "e")
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


def test_cuda_device_without_cuda_is_one_clear_error():
    if torch.cuda.is_available():
        pytest.skip("CUDA present")
    with pytest.raises(InputError, match="--device cuda"):
        resolve_device("cuda")
    assert resolve_device(None).type == "cpu"


def test_nan_in_a_loss_is_skipped_rolled_back_and_then_stops_naming_the_term(tiny_sequence, tmp_path, monkeypatch):
    import s3o_warp.fit as F
    from s3o_warp.fit import FitDiverged

    monkeypatch.setattr(F, "SNAPSHOT_EVERY", 1)
    cfg = _cfg(**{"coarse.steps": 2, "motion.warmup_steps": 6, "motion.steps": 2})
    orig = Fitter.motion_losses
    calls = {"n": 0}

    def nan_once(self, frames):
        calls["n"] += 1
        terms, sil, mask = orig(self, frames)
        if calls["n"] == 4:
            w, v = terms["sil"]
            terms["sil"] = (w, v * float("nan"))
        return terms, sil, mask

    monkeypatch.setattr(Fitter, "motion_losses", nan_once)
    fit(tiny_sequence, tmp_path / "once", cfg, torch.device("cpu"))
    st = torch.load(latest_checkpoint(tmp_path / "once"), weights_only=False)
    assert all(torch.isfinite(v).all() for v in st["model"].values() if v.is_floating_point())
    assert calls["n"] == 6 + 2 + 1  # the skipped step was retried

    def nan_always(self, frames):
        terms, sil, mask = orig(self, frames)
        w, v = terms["flow"]
        terms["flow"] = (w, v * float("inf"))
        return terms, sil, mask

    monkeypatch.setattr(Fitter, "motion_losses", nan_always)
    with pytest.raises(FitDiverged, match="loss term 'flow'"):
        fit(tiny_sequence, tmp_path / "always", cfg, torch.device("cpu"))


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


def test_temporal_smoothness_is_the_mean_squared_first_difference():
    from s3o_warp.motion import losses as L

    t = torch.arange(6, dtype=torch.float64)
    line = torch.stack([2 * t, -t], 1)  # constant velocity
    assert float(L.temporal_smoothness(line)) == pytest.approx((4 + 1) / 2)
    assert float(L.temporal_smoothness(t[:1])) == 0.0


def test_a_constant_extra_turn_of_the_root_costs_its_rate_squared(tiny_sequence, tmp_path):
    """The root's rotation is an offset from the hypothesis' constant turn: the motion smoothness term (on first
    differences) holds the turn rate at the hypothesis'."""
    cfg = _cfg(**{"coarse.steps": 2})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    m = f.model
    T = m.num_frames
    with torch.no_grad():
        for p in (m.root_aa, m.root_t, m.bone_aa, m.bone_t):
            p.zero_()
        m.root_aa[:, 1] = 0.01 * torch.arange(T, dtype=torch.float32)  # 0.57 degrees per frame more turn
    terms, _, _ = f.motion_losses(torch.arange(0, 3))
    assert float(terms["smooth"][1].detach()) == pytest.approx(0.01**2 / 3, rel=1e-4)


def test_sweep_seeds_new_frames_from_the_nearest_visited_one(tiny_sequence, tmp_path):
    cfg = _cfg(**{"coarse.steps": 2})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    m = f.model
    m.visited.zero_()
    m.visited[[2, 3]] = True
    g = torch.Generator().manual_seed(0)
    params = (m.root_aa, m.root_t, m.bone_aa, m.bone_t)
    with torch.no_grad():
        for p in params:
            p.data[2] = torch.randn(p.shape[1:], generator=g)
            p.data[3] = torch.randn(p.shape[1:], generator=g)
    seed_unvisited(m, torch.arange(2, 7), f.coarse.canonical)  # 4, 5, 6 are new, 3 their nearest visited frame
    for p in params:
        assert not torch.equal(p.data[2], p.data[3])
        for fr in (4, 5, 6):
            torch.testing.assert_close(p.data[fr], p.data[3], rtol=0, atol=0)
    assert m.visited[2:7].all()


@pytest.mark.parametrize("stride", [0, 1, 3])
def test_sweep_moves_outward_by_its_stride(tiny_sequence, tmp_path, stride):
    cfg = _cfg(**{"coarse.steps": 2, "motion.batch_frames": 4})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    T, n, c = data.num_frames, 4, f.coarse.canonical
    starts = f.windows.sweep_starts(stride)
    s0 = min(max(c - n // 2, 0), T - n)
    assert starts[0] == s0 and 0 in starts and T - n in starts and len(set(starts)) == len(starts)
    step = stride or n // 2
    right = [s for s in starts if s > s0]
    left = [s for s in starts if s < s0]
    assert right == sorted(right) and left == sorted(left, reverse=True)  # outward on each side
    for side in (right, left):  # consecutive stages move by the stride (the last may be shorter, to reach the end)
        gaps = np.abs(np.diff([s0] + side))
        assert (gaps[:-1] == step).all() and 0 < gaps[-1] <= step if len(gaps) else True


def test_a_shared_principal_point_starts_where_the_per_frame_ones_do_and_stays_one(tiny_sequence, tmp_path):
    from s3o_warp.model import S3OModel

    short = {"coarse.steps": 2, "motion.warmup_steps": 4, "motion.steps": 4}
    cfg, shared_cfg = _cfg(**short), _cfg(**short, **{"motion.principal_point": "shared"})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    per, shared = (S3OModel(coarse_model(data, c).init) for c in (cfg, shared_cfg))
    frames = torch.arange(data.num_frames)
    with torch.no_grad():
        Kp, Ks = per.intrinsics_frame(frames), shared.intrinsics_frame(frames)
        H, W = data.frame_size
        # the crops follow the object, so the per-frame points wander over the frame; the shared one is its centre
        assert (Kp[:, :2, 2] - Kp[:1, :2, 2]).abs().max() > 2.0
        assert torch.allclose(Ks[:, :2, 2], torch.tensor([(W - 1) / 2, (H - 1) / 2]).expand(len(frames), 2), atol=1e-3)
        assert torch.allclose(Ks[:, 0, 0], Kp[:, 0, 0])
        # the root starts where each crop's centre put the object: the same full-frame pixels, to perspective's
        # difference over the object's depth (a fraction of a pixel)
        def pixels(m, K):
            v = m(frames)
            return (v @ K.transpose(1, 2))[..., :2] / v[..., 2:]

        px_per, px_shared = pixels(per, Kp), pixels(shared, Ks)
        assert (px_per - px_shared).norm(dim=-1).max() < 0.5, (px_per - px_shared).norm(dim=-1).max()
        assert (per.root_t[:, :2] - shared.root_t[:, :2]).abs().max() > 1e-3  # the root took the crops' shift
        assert (per.root_R0 - shared.root_R0).abs().max() > 1e-4  # and turned with the ray to each crop's centre
    # a fit keeps one principal point (the exported intrinsics)
    run = tmp_path / "run"
    fit(tiny_sequence, run, shared_cfg, torch.device("cpu"))
    K = np.load(run / "motion.npz")["K"]
    assert np.abs(K[:, :2, 2] - K[:1, :2, 2]).max() < 1e-3 and np.abs(K[0, :2, 2] - [(W - 1) / 2, (H - 1) / 2]).max() > 0


def test_the_shared_principal_points_start_shows_each_crops_view():
    """Hand-made: crops far off the frame's centre (a ray 0.2 rad off the axis). The root on the crop's axis lands on
    the crop's centre, and the side of the object facing the camera (the camera's direction in the object frame) is
    the crop model's; moving the root sideways alone lands there too but shows another side."""
    from s3o_warp.geometry import axis_angle_to_matrix
    from s3o_warp.model import root_for_shared_principal_point

    f, pp, S = 500.0, (319.5, 239.5), 64
    centres = torch.tensor([[420.0, 239.5], [319.5, 140.0], [250.0, 330.0]], dtype=torch.float64)
    scale = 0.5  # crop pixels per frame pixel
    A = torch.zeros(3, 3, 3, dtype=torch.float64)  # crop -> frame: frame = crop / scale + offset
    A[:, 0, 0] = A[:, 1, 1] = 1 / scale
    A[:, 2, 2] = 1
    A[:, :2, 2] = centres - (S - 1) / 2 / scale
    R0 = axis_angle_to_matrix(torch.tensor([[0.3, -0.5, 0.2]], dtype=torch.float64)).expand(3, 3, 3)
    t0 = torch.tensor([[0.0, 0.0, 4.0]], dtype=torch.float64).expand(3, 3)
    R, t = root_for_shared_principal_point(R0, t0, A, S, f, pp)
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(3, 3, 3), atol=1e-12)
    px = f * t[:, :2] / t[:, 2:] + torch.tensor(pp, dtype=torch.float64)
    assert torch.allclose(px, centres, atol=1e-9), px
    assert torch.allclose(t.norm(dim=1), t0.norm(dim=1))  # as far from the camera
    side = lambda R, t: torch.einsum("tji,tj->ti", R, -t) / t.norm(dim=1, keepdim=True)  # noqa: E731
    assert torch.allclose(side(R, t), side(R0, t0), atol=1e-12)
    shifted = t0.clone()
    shifted[:, :2] += (centres - torch.tensor(pp, dtype=torch.float64)) * t0[:, 2:] / f
    turned_by = torch.arccos((side(R0, shifted) * side(R0, t0)).sum(1).clamp(-1, 1))
    assert (turned_by > 0.15).all(), turned_by  # the old start showed the object 0.15-0.2 rad from the crop's side


def test_known_turn_rate_skips_the_scoring(tiny_sequence, tmp_path):
    cfg = _cfg(**{"coarse.steps": 2, "motion.warmup_steps": 2, "motion.steps": 2, "motion.turn_rate": 1.5})
    run = tmp_path / "run"
    fit(tiny_sequence, run, cfg, torch.device("cpu"))
    rec = next(json.loads(l) for l in (run / "log.jsonl").read_text().splitlines() if '"hypotheses"' in l)
    assert rec["rates_deg_per_frame"] == [1.5] and rec["chosen"] == 1.5


def test_streamed_frames_give_the_same_fit_as_resident_ones(tiny_sequence, tmp_path):
    base = {"coarse.steps": 3, "motion.warmup_steps": 4, "motion.steps": 4}
    fit(tiny_sequence, tmp_path / "res", _cfg(**base), torch.device("cpu"))
    fit(tiny_sequence, tmp_path / "str", _cfg(**base, **{"data.resident_max_frames": 2}), torch.device("cpu"))
    assert list((tmp_path / "str" / "cache").glob("crops_*.npy")), "long sequences stream crops from a memory map"
    pa, pb = _final_params(tmp_path / "res"), _final_params(tmp_path / "str")
    for k in pa:
        torch.testing.assert_close(pb[k], pa[k], rtol=0, atol=0, msg=k)


def test_coarse_fit_keeps_the_lifted_depth(tiny_sequence, tmp_path):
    """One view says nothing about depth: the coarse fit moves vertices in its image plane only."""
    cfg = _cfg(**{"coarse.steps": 15, "motion.warmup_steps": 0, "motion.steps": 0})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    v0 = f.model.verts.detach().clone()
    f.run()
    v1 = f.model.verts.detach()
    assert (v1[:, :2] - v0[:, :2]).abs().max() > 1e-3  # the silhouette moved them
    dz = float((v1[:, 2] - v0[:, 2]).abs().max())
    assert dz == 0.0, dz
    # the relative Laplacian is zero at its reference shape and grows with a bumpy change
    from s3o_warp.kernels.regularisers import laplacian_loss

    assert float(laplacian_loss(v1 - v1, f.model.faces)) == 0.0
    assert float(laplacian_loss(torch.randn_like(v1) * 0.01, f.model.faces)) > 0


def _joint_fitter(tiny_sequence, tmp_path):
    """A Fitter in its joint phase after 3 steps on frames 0-3 (the bones have some motion). The M-step tests'
    cases (a far leg never seen moving, the shortest inner bone) were picked on this state, made with the medium
    preset's own finest flow level (1), which is pinned so the state stays."""
    cfg = _cfg(**{"coarse.steps": 5, "motion.warmup_steps": 5})
    with mock.patch.object(video_flow, "FLOW_FINEST_SCALE", 1):
        data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    f.phase = "joint"
    f.opt = f.make_optimizer()
    frames = torch.arange(0, 4)
    for _ in range(3):
        f.opt.zero_grad()
        terms, _, _ = f.motion_losses(frames)
        sum(w * v for w, v in terms.values()).backward()
        f.step_window(frames)
    return cfg, data, f, frames


def _posed_and_loss(f, frames):
    """The posed mesh and the motion loss of a Fitter on ``frames`` (no gradients)."""
    with torch.no_grad():
        return f.model(frames).clone(), float(sum(w * v for w, v in f.motion_losses(frames)[0].values()))


def _assert_no_jump(before, after, loss0, loss1):
    """A skeleton edit moved the posed mesh by < 1 % of its diagonal (mean) and the loss by < 5 %."""
    diag = float((before.amax((0, 1)) - before.amin((0, 1))).norm())
    assert float((after - before).norm(dim=-1).mean()) < 0.01 * diag
    assert abs(loss1 - loss0) < 0.05 * loss0, (loss0, loss1)


@pytest.mark.parametrize("epoch", [0, 2])  # 0: shift + growth, 2 (= e1): upsampling
def test_m_step_keeps_the_posed_mesh_and_the_loss(tiny_sequence, tmp_path, epoch):
    from s3o_warp.skeleton.mstep import m_step

    cfg, data, f, frames = _joint_fitter(tiny_sequence, tmp_path)
    before, loss0 = _posed_and_loss(f, frames)
    B0 = f.model.num_bones
    if epoch == 0:  # make the growth test fire: pretend every part was half as long at the start
        from s3o_warp.skeleton import measures as sk

        X, W = f.model.verts.detach().double().numpy(), f.model.skinning().detach().double().numpy()
        f.skel.extents = 0.4 * sk.part_extents(X, W)
    changed = m_step(f.model, f.opt, data, cfg, f.skel, epoch)
    assert changed and f.model.num_bones >= B0
    if epoch == cfg.skeleton.e1:
        assert f.model.num_bones > B0
    after, loss1 = _posed_and_loss(f, frames)
    _assert_no_jump(before, after, loss0, loss1)  # measured: 0.1-0.25 % of the diagonal, 0.1-0.4 % of the loss
    # the optimiser follows the new parameters and can step
    f.opt.zero_grad()
    terms, _, _ = f.motion_losses(frames)
    sum(w * v for w, v in terms.values()).backward()
    f.step_window(frames)
    assert len(f.skel.parents) == f.model.num_bones


def test_min_section_vertices_stops_the_m_steps_splits(tiny_sequence, tmp_path, monkeypatch):
    """mstep.MIN_SECTION_VERTICES reaches the upsampling and joint creation: when no bone owns enough vertices
    for two sections, neither splits one; at the default both do."""
    from s3o_warp.skeleton import mstep
    from s3o_warp.skeleton.mstep import m_step

    cfg, data, f, frames = _joint_fitter(tiny_sequence, tmp_path)
    sc, B0, default = cfg.skeleton, f.model.num_bones, mstep.MIN_SECTION_VERTICES
    monkeypatch.setattr(mstep, "MIN_SECTION_VERTICES", f.model.verts.shape[0])
    assert not m_step(f.model, f.opt, data, cfg, f.skel, sc.e1) and f.model.num_bones == B0  # no upsampling
    monkeypatch.setattr(mstep, "MIN_SECTION_VERTICES", default)
    assert m_step(f.model, f.opt, data, cfg, f.skel, sc.e1) and f.model.num_bones > B0
    sc.t_o, sc.t_d = 2.0, 0.0  # no merge; every bone qualifies for a joint
    monkeypatch.setattr(mstep, "MIN_BONE_LENGTH", 0.0)  # no pruning
    B1 = f.model.num_bones
    monkeypatch.setattr(mstep, "MIN_SECTION_VERTICES", f.model.verts.shape[0])
    assert not m_step(f.model, f.opt, data, cfg, f.skel, sc.e1 + 1) and f.model.num_bones == B1
    monkeypatch.setattr(mstep, "MIN_SECTION_VERTICES", default)
    assert m_step(f.model, f.opt, data, cfg, f.skel, sc.e1 + 1) and f.model.num_bones > B1
    assert f.skel.history[-1]["operation"] == "joint"


def test_joint_samples_reach_the_joints_and_the_m_step(tiny_sequence, tmp_path, monkeypatch):
    """The joints are taken over the surface samples (each face's 4 x 4 grid, mstep.JOINT_SAMPLES), not over the
    vertices (1, the paper), and the M-step's lengths and joint creation run on them."""
    from s3o_warp.skeleton import mstep
    from s3o_warp.skeleton import measures as sk
    from s3o_warp.skeleton.mstep import bone_length_variation, m_step, refresh_joints

    cfg, data, f, frames = _joint_fitter(tiny_sequence, tmp_path)
    sc = cfg.skeleton
    assert m_step(f.model, f.opt, data, cfg, f.skel, sc.e1) and len(f.skel.joints)
    J4 = f.skel.joint_positions.copy()
    X, W = f.model.verts.detach().double().numpy(), f.model.skinning().detach().double().numpy()
    s = sk.surface_samples(X, f.model.faces.numpy(), f.model.bone_centers.detach().double().numpy(),
                           f.model.precisions().detach().double().numpy(), 4)
    J = sk.joint_positions(X, W, f.skel.joints, t_r=sc.t_r, samples=s)
    np.testing.assert_allclose(J4, sk.centre_in_body(J, X, f.model.faces.numpy(), max_depth=mstep.JOINT_DEPTH))
    monkeypatch.setattr(mstep, "JOINT_SAMPLES", 1)
    refresh_joints(f.model, f.skel, sc)
    assert not np.allclose(f.skel.joint_positions, J4)
    monkeypatch.undo()
    split, E = bone_length_variation(f.model, data, f.skel, cfg)
    np.testing.assert_allclose(E, sk.bone_endpoints(X, W, f.skel.joints, t_r=sc.t_r, far_fraction=mstep.FAR_FRACTION,
                                                    samples=s))
    sc.t_o, sc.t_d = 2.0, 0.0  # every bone qualifies for a joint
    monkeypatch.setattr(mstep, "MIN_BONE_LENGTH", 0.0)
    B1 = f.model.num_bones
    assert m_step(f.model, f.opt, data, cfg, f.skel, sc.e1 + 1) and f.model.num_bones > B1
    assert len(f.skel.parents) == f.model.num_bones == len(f.skel.joints) + 1


def test_m_step_splits_bones_that_bend_and_keeps_the_loss(tiny_sequence, tmp_path, monkeypatch):
    """Bones whose halves' unexplained motion is above t_u get a joint, end bones (one joint) and inner bones (two
    joints or more) alike (here t_u < 0: every bone seen in enough frames); above every bone's, nothing splits.
    The loss does not jump."""
    from s3o_warp.skeleton import mstep
    from s3o_warp.skeleton.mstep import bone_length_variation, end_bone_bending, m_step

    cfg, data, f, frames = _joint_fitter(tiny_sequence, tmp_path)
    sc = cfg.skeleton
    assert m_step(f.model, f.opt, data, cfg, f.skel, sc.e1)  # upsampling: the joints the refinement reads
    sc.t_o, sc.t_d = 2.0, 1e9  # no merge, no eq. 6 joint
    monkeypatch.setattr(mstep, "MIN_BONE_LENGTH", 0.0)  # no pruning
    B0 = f.model.num_bones
    count = np.bincount(f.skel.joints.ravel(), minlength=B0)
    _, E = bone_length_variation(f.model, data, f.skel, cfg)
    r = end_bone_bending(f.model, data, f.skel, E, cfg)
    assert np.isfinite(r[count == 1]).any() and np.isfinite(r[count >= 2]).any()
    assert not np.isfinite(r[count == 0]).any()
    assert ((r[np.isfinite(r)] >= 0) & (r[np.isfinite(r)] <= 2)).all()
    sc.t_u = float(np.nanmax(r)) + 0.01
    assert not m_step(f.model, f.opt, data, cfg, f.skel, sc.e1 + 1) and f.model.num_bones == B0
    before, loss0 = _posed_and_loss(f, frames)
    sc.t_u = -1.0
    assert m_step(f.model, f.opt, data, cfg, f.skel, sc.e1 + 1)
    assert f.model.num_bones == B0 + int(np.isfinite(r).sum()) and f.skel.history[-1]["operation"] == "joint"
    after, loss1 = _posed_and_loss(f, frames)
    _assert_no_jump(before, after, loss0, loss1)


def test_m_step_prunes_short_bones_and_keeps_the_loss(tiny_sequence, tmp_path, monkeypatch):
    """After e1 the M-step merges bones shorter than mstep.MIN_BONE_LENGTH into their parents; the
    posed mesh and the loss barely move (the short bone's few vertices follow its parent)."""
    from s3o_warp.skeleton import mstep
    from s3o_warp.skeleton import measures as sk
    from s3o_warp.skeleton.mstep import joint_samples, m_step

    cfg, data, f, frames = _joint_fitter(tiny_sequence, tmp_path)
    cfg.skeleton.t_o, cfg.skeleton.t_d, cfg.skeleton.t_u = 2.0, 1e9, float("inf")  # no merge, no joint: pruning only
    X, W = f.model.verts.detach().double().numpy(), f.model.skinning().detach().double().numpy()
    E = sk.bone_endpoints(X, W, f.skel.joints, t_r=cfg.skeleton.t_r, samples=joint_samples(f.model))
    L = sk.bone_lengths(E, X) / sk.size_of(X)
    inner = np.flatnonzero(np.bincount(f.skel.parents[f.skel.parents >= 0], minlength=len(L)) > 0)
    monkeypatch.setattr(mstep, "MIN_BONE_LENGTH", float(L[inner].min() * 1.001))  # the shortest inner bone is short
    # bones that own no vertex go too, whatever their length (prune_short_bones); the fit's state may hold some
    empty = np.bincount(sk.assign_parts(W), minlength=len(L))[: len(L)] == 0
    empty[inner[np.argmin(L[inner])]] = False
    before, loss0 = _posed_and_loss(f, frames)
    B0 = f.model.num_bones
    assert m_step(f.model, f.opt, data, cfg, f.skel, cfg.skeleton.e1 + 1)
    B1 = B0 - 1 - int(empty.sum())
    assert f.model.num_bones == B1 and f.skel.history[-1]["operation"] == "prune"
    assert len(f.skel.parents) == B1 and (f.skel.parents == -1).sum() == 1
    after, loss1 = _posed_and_loss(f, frames)
    _assert_no_jump(before, after, loss0, loss1)  # measured: 0.08 % of the diagonal, 2.1 % of the loss (9 -> 8 bones)
    # 0 = the paper: nothing is pruned
    monkeypatch.setattr(mstep, "MIN_BONE_LENGTH", 0.0)
    assert not m_step(f.model, f.opt, data, cfg, f.skel, cfg.skeleton.e1 + 1)


def test_the_fits_end_merges_bones_that_own_no_vertex(tiny_sequence, tmp_path):
    """An inner bone that owns no vertex when the fit ends is merged into its parent
    (its child re-hangs there, a joint between them replaces its two), and the posed mesh and the loss stay."""
    from s3o_warp.skeleton.mstep import m_step

    cfg, data, f, frames = _joint_fitter(tiny_sequence, tmp_path)
    assert m_step(f.model, f.opt, data, cfg, f.skel, cfg.skeleton.e1)  # upsampling: chains with inner bones
    P = f.skel.parents
    inner = [b for b in range(len(P)) if P[b] >= 0 and (P == b).any()]
    b = inner[0]
    before, loss0 = _posed_and_loss(f, frames)
    with torch.no_grad():  # the bone's Gaussian moves far off: it owns nothing and weighs ~0 everywhere
        f.model.bone_centers[b] += 10.0 * (f.model.verts.amax(0) - f.model.verts.amin(0)).norm()
    assert (f.model.skinning().argmax(1) != b).all()
    B0, parent, kids = f.model.num_bones, int(P[b]), np.flatnonzero(P == b)
    f.final_skeleton()
    assert f.model.num_bones == B0 - 1 and f.skel.history[-1]["operation"] == "prune empty (end)"
    new = lambda x: x - (x > b)  # noqa: E731 - indices after b shift down by one
    assert [int(f.skel.parents[new(k)]) for k in kids] == [new(parent)] * len(kids)
    assert {(new(parent), new(int(k))) for k in kids} <= {tuple(j) for j in f.skel.joints.tolist()}
    after, loss1 = _posed_and_loss(f, frames)  # as before the bone emptied (its regulariser aside)
    _assert_no_jump(before, after, loss0, loss1)
    f.final_skeleton()  # nothing empty any more
    assert f.model.num_bones == B0 - 1


def test_m_step_does_not_merge_on_a_few_frames(tiny_sequence, tmp_path, caplog, monkeypatch):
    """A pair that agrees (> t_o) merges when compared on enough frame pairs, and is kept apart, with one log
    line, when mstep.MIN_FRAMES_FRACTION asks for more frame pairs than it was compared on."""
    from s3o_warp.skeleton import mstep
    from s3o_warp.skeleton.mstep import bone_motion_similarity, merge_min_frames, m_step

    cfg, data, f, frames = _joint_fitter(tiny_sequence, tmp_path)
    sc = cfg.skeleton
    sc.t_d, sc.t_u = 1e9, float("inf")  # merges only
    monkeypatch.setattr(mstep, "MIN_BONE_LENGTH", 0.0)
    S, N = bone_motion_similarity(f.model, data, cfg)
    P, B0 = f.skel.parents, f.model.num_bones
    kids = [b for b in range(B0) if P[b] >= 0 and np.isfinite(S[b, P[b]])]
    assert kids, "expected a parent-child pair compared on some frames"
    b = max(kids, key=lambda c: S[c, P[c]])
    sc.t_o = float(S[b, P[b]]) - 1e-4  # b and its parent (and nothing else, or more alike pairs) agree
    merges = sum(1 for c in kids if S[c, P[c]] > sc.t_o)
    g = copy.deepcopy(f)
    g.opt = g.make_optimizer()
    monkeypatch.setattr(mstep, "MIN_FRAMES_FRACTION", 0.0)
    assert merge_min_frames(data.num_frames) == mstep.MIN_FRAMES
    assert m_step(f.model, f.opt, data, cfg, f.skel, sc.e1 + 1) and f.model.num_bones == B0 - merges
    gc = g.cfg.skeleton
    gc.t_o, gc.t_d, gc.t_u = sc.t_o, 1e9, float("inf")
    monkeypatch.setattr(mstep, "MIN_FRAMES_FRACTION", min(1.0, (int(N[b, P[b]]) + 0.5) / (data.num_frames - 1)))
    assert merge_min_frames(data.num_frames) == int(N[b, P[b]]) + 1  # one frame pair more than b was compared on
    with caplog.at_level(logging.INFO, logger="s3o_warp.skeleton.mstep"):
        m_step(g.model, g.opt, data, g.cfg, g.skel, gc.e1 + 1)
    assert g.model.num_bones == B0 - sum(1 for c in kids if S[c, P[c]] > sc.t_o and N[c, P[c]] > N[b, P[b]])
    assert any("not merged" in r.getMessage() and str(b) in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("method", ["marching", "isotropic"])
def test_even_resampling_in_the_fit_keeps_the_render_and_the_loss(tiny_sequence, tmp_path, method, monkeypatch):
    import s3o_warp.resample as rs
    from s3o_warp.kernels.raster import rasterize

    cfg, data, f, frames = _joint_fitter(tiny_sequence, tmp_path)
    monkeypatch.setattr(rs, "METHODS", (method,))  # this method alone
    m, S = f.model, data.crop_size

    def state():
        with torch.no_grad():
            fi, _, _ = rasterize(m(frames), m.faces, m.intrinsics_crop(frames), (S, S))
            return (fi >= 0), float(sum(w * v for w, v in f.motion_losses(frames)[0].values()))

    sil0, loss0 = state()
    n0, bones_state = m.verts.shape[0], f.opt.state[m.bone_aa]["exp_avg"].clone()
    f.resample_mesh()
    sil1, loss1 = state()
    iou = float((sil0 & sil1).sum() / (sil0 | sil1).sum())
    assert iou > 0.9, iou  # the same surface, posed by the same skeleton
    assert abs(loss1 - loss0) < 0.15 * loss0, (loss0, loss1)
    assert abs(m.verts.shape[0] - len(f.coarse.init.verts)) <= 0.15 * len(f.coarse.init.verts) or m.verts.shape[0] != n0
    if method == "isotropic":  # no grid: the count lands near the target
        assert abs(m.verts.shape[0] - len(f.coarse.init.verts)) <= 0.15 * len(f.coarse.init.verts)
    assert f.ctx.edges.max() < m.verts.shape[0]
    # the optimiser keeps the motion's Adam state and steps the new vertices
    torch.testing.assert_close(f.opt.state[m.bone_aa]["exp_avg"], bones_state)
    v0 = m.verts.detach().clone()
    f.opt.zero_grad()
    terms, _, _ = f.motion_losses(frames)
    sum(w * v for w, v in terms.values()).backward()
    f.step_window(frames)
    assert not torch.equal(v0, m.verts.detach())


def test_a_refused_resampling_keeps_the_mesh_and_its_optimiser_state(tiny_sequence, tmp_path, monkeypatch):
    """When even_resample gives the mesh back (it would lose more than ResampleSettings.max_lost), the fit keeps its
    vertex parameter, the vertices' Adam state and the Laplacian reference, and logs the resampling as kept."""
    import s3o_warp.resample as rs

    cfg, data, f, frames = _joint_fitter(tiny_sequence, tmp_path)
    m = f.model
    f.opt.zero_grad()
    terms, _, _ = f.motion_losses(frames)
    sum(w * v for w, v in terms.values()).backward()
    f.step_window(frames)  # the vertices have Adam state now
    seen = []

    def refuse(verts, faces, settings=None, attributes=None):
        seen.append((settings.method, settings.target_vertices))
        return verts.detach().clone(), faces.detach().clone(), attributes.detach().clone()

    monkeypatch.setattr(rs, "even_resample", refuse)
    verts, lap_ref, state = m.verts, f.ctx.lap_ref, {k: v.clone() for k, v in f.opt.state[m.verts].items()}
    f.resample_mesh()
    # the target reaches the resampling; refused by marching, isotropic is tried on the same mesh
    n = len(f.coarse.init.verts)
    assert seen == [("marching", n), ("isotropic", n)]
    assert m.verts is verts and f.ctx.lap_ref is lap_ref
    for k, v in state.items():
        torch.testing.assert_close(f.opt.state[m.verts][k], v)
    assert f.history[-1]["what"] == "resample" and f.history[-1]["kept"] is True and f.history[-1]["method"] is None


def test_a_resampling_refused_by_marching_is_done_by_the_fallback(tiny_sequence, tmp_path, monkeypatch):
    """When marching would lose too much, isotropic remeshing's result is used (and logged)."""
    import s3o_warp.resample as rs

    cfg, data, f, frames = _joint_fitter(tiny_sequence, tmp_path)
    m = f.model
    real = rs.even_resample
    seen = []

    def marching_refuses(verts, faces, settings=None, attributes=None):
        seen.append(settings.method)
        if settings.method == "marching":
            return verts.detach().clone(), faces.detach().clone(), attributes.detach().clone()
        return real(verts, faces, settings, attributes)

    monkeypatch.setattr(rs, "even_resample", marching_refuses)
    verts = m.verts
    f.resample_mesh()
    assert seen == ["marching", "isotropic"]
    assert m.verts is not verts and f.ctx.edges.max() < m.verts.shape[0]
    assert f.history[-1]["kept"] is False and f.history[-1]["method"] == "isotropic"


def test_cli_fits_a_video_file_with_a_mask_folder(tiny_sequence, tmp_path):
    import cv2

    from s3o_warp.cli import main as cli_main

    frames = sorted((tiny_sequence / "images").glob("*.png"))
    first = cv2.imread(str(frames[0]))
    path = tmp_path / "clip.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 12.0, (first.shape[1], first.shape[0]))
    for f in frames:
        vw.write(cv2.imread(str(f)))
    vw.release()
    run = tmp_path / "run"
    rc = cli_main([str(path), "--masks", str(tiny_sequence / "masks"), "--out", str(run), "--preset", "smoke",
                   "--set", "data.crop_size=64"])
    assert rc == 0
    m = json.loads((run / "metrics.json").read_text())
    assert m["frames"] == len(frames)
    assert m["mask_iou"]["mean"] > 0.3 and m["pck_t"] is not None  # masks and keypoints beside the mask folder
    assert np.load(run / "motion.npz")["fps"] == pytest.approx(12.0)
    assert (run / "renders" / "overlay.mp4").is_file() or (run / "renders" / "overlay.gif").is_file()


def test_coverage_term_follows_its_weight_and_pulls_the_bones(tiny_sequence, tmp_path, monkeypatch):
    """motion.w_cover adds the coverage term in both phases (0: none) and its gradient reaches the motion."""
    import s3o_warp.motion.objective as O
    from s3o_warp.geometry import project
    from s3o_warp.kernels.raster import rasterize
    from s3o_warp.motion import losses as L

    monkeypatch.setattr(O, "COVER_PIXELS", 0)  # every uncovered pixel: the term is compared exactly below
    cfg = _cfg(**{"coarse.steps": 2, "motion.w_cover": 0.5})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    frames = torch.arange(0, 3)
    f.phase = "warmup"
    assert f.motion_losses(frames)[0]["cover"][0] == 0.5
    f.cfg.motion.w_cover = 0.0
    assert "cover" not in f.motion_losses(frames)[0]
    f.cfg.motion.w_cover = 0.5
    f.phase = "joint"
    terms = f.motion_losses(frames)[0]
    w, v = terms["cover"]
    assert w == 0.5
    m, S = f.model, data.crop_size
    with torch.no_grad():
        verts = m(frames)
        K = m.intrinsics_crop(frames)
        fi, _, _ = rasterize(verts, m.faces, K, (S, S))
        uncovered = (data.masks[frames] > 0.5) & (fi < 0)
        assert uncovered.any()  # the coarse shape does not cover every frame's mask yet
        assert float(v) == pytest.approx(float(L.coverage_loss(project(verts, K), uncovered)), rel=1e-5)
    v.backward()
    assert float(m.root_t.grad.abs().sum()) > 0 or float(m.bone_aa.grad.abs().sum()) > 0


def test_joint_attachment_loss_against_a_dense_twin():
    """Each joint carried by its two bones: the mean squared gap over the object's size squared; zero when the
    bones move as one rigid piece; float64 gradcheck."""
    from s3o_warp.motion import losses as L
    from s3o_warp.geometry import axis_angle_to_matrix

    g = torch.Generator().manual_seed(0)
    t, B = 3, 4
    aa = (0.3 * torch.randn(t, B, 3, generator=g)).double().requires_grad_()
    tr = (0.1 * torch.randn(t, B, 3, generator=g)).double().requires_grad_()
    joints = torch.tensor([[0, 1], [1, 2], [1, 3]])
    pos = torch.randn(3, 3, generator=g).double()

    def rt(aa, tr):
        return torch.cat([axis_angle_to_matrix(aa.reshape(-1, 3)).reshape(t, B, 3, 3), tr[..., None]], -1)

    def twin(aa, tr):
        T = rt(aa, tr)
        total = 0.0
        for f in range(t):
            for (a, b), j in zip(joints.tolist(), pos):
                pa = T[f, a, :, :3] @ j + T[f, a, :, 3]
                pb = T[f, b, :, :3] @ j + T[f, b, :, 3]
                total = total + ((pa - pb) ** 2).sum()
        return total / (t * len(joints)) / 2.0**2

    got = L.joint_attachment_loss(rt(aa, tr), joints, pos, 2.0)
    assert float(got.detach()) == pytest.approx(float(twin(aa, tr).detach()), rel=1e-12)
    assert torch.autograd.gradcheck(lambda a, b: L.joint_attachment_loss(rt(a, b), joints, pos, 2.0), (aa, tr))
    same = rt(aa[:, :1].expand(t, B, 3), tr[:, :1].expand(t, B, 3))  # every bone moved like bone 0
    assert float(L.joint_attachment_loss(same, joints, pos, 2.0).detach()) == pytest.approx(0.0, abs=1e-20)
    one = torch.zeros(1, 2, 3, 4, dtype=torch.float64)
    one[..., :3] = torch.eye(3, dtype=torch.float64)
    one[0, 1, :, 3] = torch.tensor([0.0, 0.3, 0.4], dtype=torch.float64)  # bone 1 slid by 0.5 off its joint
    assert float(L.joint_attachment_loss(one, torch.tensor([[0, 1]]), pos[:1], 2.0)) == pytest.approx(0.25 / 4)
    assert float(L.joint_attachment_loss(one, torch.zeros(0, 2, dtype=torch.long), pos[:0], 2.0)) == 0.0


def test_joint_term_follows_its_weight_and_uses_the_skeletons_joints(tiny_sequence, tmp_path):
    """motion.w_joint adds the joint term in both phases (0 = off), on the kinematic tree's joints and the
    object's size, and its gradient reaches the bones' motion."""
    from s3o_warp.motion import losses as L

    cfg = _cfg(**{"coarse.steps": 2, "motion.w_joint": 0.0})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    frames = torch.arange(0, 3)
    assert "joint" not in f.motion_losses(frames)[0]  # 0 = off
    assert _cfg().motion.w_joint == 10.0  # on by default
    cfg = _cfg(**{"coarse.steps": 2, "motion.w_joint": 3.0})
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path / "b", torch.device("cpu"))
    m = f.model
    assert len(f.skel.joints) == m.num_bones - 1
    with torch.no_grad():
        m.bone_t[:, 1:] += 0.05  # bones off their joints
    for phase in ("warmup", "joint"):
        f.phase = phase
        w, v = f.motion_losses(frames)[0]["joint"]
        assert w == 3.0
        J = torch.as_tensor(f.skel.joints)
        P = torch.as_tensor(f.skel.joint_positions, dtype=torch.float32)
        size = float((m.verts.detach().max(0).values - m.verts.detach().min(0).values).norm())
        assert float(v.detach()) == pytest.approx(float(L.joint_attachment_loss(m.bone_rt(frames), J, P, size).detach()), rel=1e-5)
        assert float(v.detach()) > 0
    m.bone_t.grad = None
    v.backward()
    assert float(m.bone_t.grad.abs().sum()) > 0
    with torch.no_grad():
        m.bone_aa[:, 1:] += 0.2  # rotations, so that where the joints sit matters
    v1 = float(f.motion_losses(frames)[0]["joint"][1].detach())
    f.skel.joint_positions = f.skel.joint_positions + [0.1, 0.0, 0.0]  # an M-step replaces the joints: the term follows
    w, v2 = f.motion_losses(frames)[0]["joint"]
    assert float(v2.detach()) != pytest.approx(v1, rel=1e-3)
    P2 = torch.as_tensor(f.skel.joint_positions, dtype=torch.float32)
    assert float(v2.detach()) == pytest.approx(float(L.joint_attachment_loss(m.bone_rt(frames), J, P2, size).detach()), rel=1e-5)


def test_canonical_frame_setting_picks_the_lifted_frame(tiny_sequence, tmp_path):
    """coarse.canonical_frame overrides the automatic choice (the lift and the anchor of the fit follow it);
    a frame outside the sequence is one ConfigError naming the setting."""
    from s3o_warp.coarse.model import coarse_model
    from s3o_warp.data.store import prepare_data

    cfg = smoke_config()
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    auto = coarse_model(data, cfg).canonical
    forced = (auto + 3) % data.num_frames
    res = coarse_model(data, smoke_config(**{"coarse.canonical_frame": forced}))
    assert res.canonical == forced != auto
    with pytest.raises(ConfigError, match="coarse.canonical_frame=8"):  # refused before the flow is computed
        prepare_data(tiny_sequence, smoke_config(**{"coarse.canonical_frame": data.num_frames}), tmp_path / "x",
                     torch.device("cpu"))
    assert not (tmp_path / "x").exists()
