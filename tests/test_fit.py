"""The fit end to end on tiny built-in quadruped clips: it reconstructs, resumes exactly, repeats, stops on NaN."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from conftest import final_params, smoke_config, stop_in_joint_phase

from s3o_warp.errors import InputError
from s3o_warp.fit import FitInterrupted, Fitter, fit, resolve_device
from s3o_warp.run.checkpoint import latest_checkpoint

_cfg = smoke_config  # tiny_sequence: conftest.py


def test_small_fit_raises_iou_and_writes_the_run_directory(tiny_sequence, tmp_path):
    cfg = _cfg(**{"coarse.steps": 30, "motion.warmup_steps": 40, "motion.steps": 60})
    run = tmp_path / "run"
    metrics = fit(tiny_sequence, run, cfg, torch.device("cpu"))
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    evals = {r["what"]: r["iou_all_frames"] for r in log if r["phase"] == "eval" and "iou_all_frames" in r}
    assert any(r.get("what") == "resample" for r in log)  # even resampling ran at the epoch ends
    steps = [r for r in log if r["phase"] in ("coarse", "warmup", "joint")]
    assert steps and all(0 <= r["surface"]["roughness"] <= 1 and -1 <= r["surface"]["normal_consistency"] <= 1
                         for r in steps)  # the canonical mesh's smoothness at every logged step
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
    from s3o_warp.evaluation.loaders import load_ground_truth, load_predictions
    from s3o_warp.evaluation.shape import Similarity, bbox_diagonal
    from s3o_warp.evaluation.skeleton import chain_coverage, limb_coverage

    pred, gt = load_predictions(run), load_ground_truth(sequence / "ground_truth")
    a = metrics["shape_3d"]["alignment"]
    sim = Similarity(a["scale"], np.array(a["rotation"]), np.array(a["translation"]))
    diag = bbox_diagonal(gt.verts)
    names = list(gt.joint_names)
    cov = limb_coverage(pred.joints_cam, gt.joints, gt.joint_parents, diag, sim, names, min_joints=1,
                          branch=False)
    need = {limb["limb"]: limb["tol_needed"] for limb in cov["limbs"]}
    head = [names.index(n) for n in ("head", "nose")]
    need["nose"] = chain_coverage(pred.joints_cam, gt.joints, head, diag, sim, min_joints=1)["tol_needed"]
    neck = [names.index(n) for n in ("withers", "neck", "head")]
    need["neck"] = chain_coverage(pred.joints_cam, gt.joints, neck, diag, sim, min_joints=1)["tol_needed"]
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


def _interrupt_resume_and_compare(seq, a, b, cfg, monkeypatch, interrupting, where: str) -> None:
    """Fit into ``b`` with ``interrupting`` as the motion losses (it asks for a stop), resume, and compare the final
    parameters with the uninterrupted fit in ``a``; ``where``: what the interrupt's message names."""
    orig = Fitter.motion_losses
    monkeypatch.setattr(Fitter, "motion_losses", interrupting)
    with pytest.raises(FitInterrupted, match=where):
        fit(seq, b, cfg, torch.device("cpu"))
    monkeypatch.setattr(Fitter, "motion_losses", orig)
    fit(seq, b, cfg, torch.device("cpu"), resume=True)
    pa, pb = final_params(a), final_params(b)
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


def test_a_stop_inside_the_resampling_resumes_with_its_m_step_run_again(tiny_sequence, tmp_path, monkeypatch):
    """Ctrl-C while the mesh is resampled after an M-step: the checkpoint is the state before that M-step, which
    the resumed fit runs again, and it ends where an uninterrupted fit ends."""
    import s3o_warp.resample as R
    from s3o_warp import interrupt

    cfg = _cfg(**{"coarse.steps": 2, "motion.warmup_steps": 2, "motion.steps": 4, "skeleton.epochs": 2})
    a, b = tmp_path / "a", tmp_path / "b"
    fit(tiny_sequence, a, cfg, torch.device("cpu"))
    orig = R._march

    def stopping(*args, **kwargs):
        interrupt.request()
        return orig(*args, **kwargs)

    monkeypatch.setattr(R, "_march", stopping)
    with pytest.raises(FitInterrupted, match=r"stopped at joint step 2 \(stopped during the even resampling\)"):
        fit(tiny_sequence, b, cfg, torch.device("cpu"))
    monkeypatch.setattr(R, "_march", orig)
    st = torch.load(latest_checkpoint(b), weights_only=False)
    assert (st["phase"], st["step"], st["pending_m_step"]) == ("joint", 2, True)
    fit(tiny_sequence, b, cfg, torch.device("cpu"), resume=True)
    pa, pb = final_params(a), final_params(b)
    assert pa.keys() == pb.keys()
    for k in pa:
        torch.testing.assert_close(pb[k], pa[k], rtol=0, atol=0, msg=f"resumed fit differs in {k}")


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
    pa, pb = final_params(tmp_path / "a"), final_params(tmp_path / "b")
    assert pa.keys() == pb.keys()
    differ = [k for k in pa if pa[k].shape != pb[k].shape or not torch.equal(pa[k], pb[k])]
    assert not differ, f"same seed, different {differ}"


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


def test_streamed_frames_give_the_same_fit_as_resident_ones(tiny_sequence, tmp_path):
    base = {"coarse.steps": 3, "motion.warmup_steps": 4, "motion.steps": 4}
    fit(tiny_sequence, tmp_path / "res", _cfg(**base), torch.device("cpu"))
    fit(tiny_sequence, tmp_path / "str", _cfg(**base, **{"data.resident_max_frames": 2}), torch.device("cpu"))
    assert list((tmp_path / "str" / "cache").glob("crops_*.npy")), "long sequences stream crops from a memory map"
    pa, pb = final_params(tmp_path / "res"), final_params(tmp_path / "str")
    for k in pa:
        torch.testing.assert_close(pb[k], pa[k], rtol=0, atol=0, msg=k)


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


def test_resume_applies_a_changed_learning_rate(tiny_sequence, tmp_path, monkeypatch):
    """``--resume --set motion.lr_shape=...``: the new rate goes into the optimiser's shape group (the checkpoint's
    optimiser state carries the old one); an unchanged rate keeps the checkpoint's."""
    cfg = _cfg(**{"coarse.steps": 4, "motion.warmup_steps": 4, "motion.steps": 6})
    run = tmp_path / "run"
    stop_in_joint_phase(monkeypatch, tiny_sequence, run, cfg)
    seen = {}
    orig_run = Fitter.run

    def capture(self):
        seen.update({g["name"]: g["lr"] for g in self.opt.param_groups})
        return orig_run(self)

    monkeypatch.setattr(Fitter, "run", capture)
    new = _cfg(**{"coarse.steps": 4, "motion.warmup_steps": 4, "motion.steps": 6, "motion.lr_shape": 0.0123})
    fit(tiny_sequence, run, new, torch.device("cpu"), resume=True)
    assert seen["shape"] == 0.0123
    assert seen["motion"] == cfg.motion.lr_motion
