"""The M-step on a fit's state (skeleton/mstep.py): each edit keeps the posed mesh and the loss."""

from __future__ import annotations

import copy
import logging

import numpy as np
import pytest
import torch
from conftest import assert_no_jump, joint_fitter, posed_and_loss, smoke_config

_cfg = smoke_config  # tiny_sequence: conftest.py


@pytest.mark.parametrize("epoch", [0, 2])  # 0: shift + growth, 2 (= e1): upsampling
def test_m_step_keeps_the_posed_mesh_and_the_loss(tiny_sequence, tmp_path, epoch):
    from s3o_warp.skeleton.mstep import m_step

    cfg, data, f, frames = joint_fitter(tiny_sequence, tmp_path)
    before, loss0 = posed_and_loss(f, frames)
    B0 = f.model.num_bones
    if epoch == 0:  # make the growth test fire: pretend every part was half as long at the start
        from s3o_warp.skeleton import measures as sk

        X, W = f.model.verts.detach().double().numpy(), f.model.skinning().detach().double().numpy()
        f.skel.extents = 0.4 * sk.part_extents(X, W)
    changed = m_step(f.model, f.opt, data, cfg, f.skel, epoch)
    assert changed and f.model.num_bones >= B0
    if epoch == cfg.skeleton.e1:
        assert f.model.num_bones > B0
    after, loss1 = posed_and_loss(f, frames)
    assert_no_jump(before, after, loss0, loss1)  # measured: 0.1-0.25 % of the diagonal, 0.1-0.4 % of the loss
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

    cfg, data, f, frames = joint_fitter(tiny_sequence, tmp_path)
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
    from s3o_warp.skeleton import joints as skj
    from s3o_warp.skeleton import mstep
    from s3o_warp.skeleton.mstep import bone_length_variation, m_step, refresh_joints

    cfg, data, f, frames = joint_fitter(tiny_sequence, tmp_path)
    sc = cfg.skeleton
    assert m_step(f.model, f.opt, data, cfg, f.skel, sc.e1) and len(f.skel.joints)
    J4 = f.skel.joint_positions.copy()
    X, W = f.model.verts.detach().double().numpy(), f.model.skinning().detach().double().numpy()
    s = skj.surface_samples(X, f.model.faces.numpy(), f.model.bone_centers.detach().double().numpy(),
                           f.model.precisions().detach().double().numpy(), 4)
    J = skj.joint_positions(X, W, f.skel.joints, t_r=sc.t_r, samples=s)
    np.testing.assert_allclose(J4, skj.centre_in_body(J, X, f.model.faces.numpy(), max_depth=mstep.JOINT_DEPTH))
    monkeypatch.setattr(mstep, "JOINT_SAMPLES", 1)
    refresh_joints(f.model, f.skel, sc)
    assert not np.allclose(f.skel.joint_positions, J4)
    monkeypatch.undo()
    split, E = bone_length_variation(f.model, data, f.skel, cfg)
    np.testing.assert_allclose(E, skj.bone_endpoints(X, W, f.skel.joints, t_r=sc.t_r, far_fraction=mstep.FAR_FRACTION,
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

    cfg, data, f, frames = joint_fitter(tiny_sequence, tmp_path)
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
    before, loss0 = posed_and_loss(f, frames)
    sc.t_u = -1.0
    assert m_step(f.model, f.opt, data, cfg, f.skel, sc.e1 + 1)
    assert f.model.num_bones == B0 + int(np.isfinite(r).sum()) and f.skel.history[-1]["operation"] == "joint"
    after, loss1 = posed_and_loss(f, frames)
    assert_no_jump(before, after, loss0, loss1)


def test_m_step_prunes_short_bones_and_keeps_the_loss(tiny_sequence, tmp_path, monkeypatch):
    """After e1 the M-step merges bones shorter than mstep.MIN_BONE_LENGTH into their parents; the
    posed mesh and the loss barely move (the short bone's few vertices follow its parent)."""
    from s3o_warp.skeleton import joints as skj
    from s3o_warp.skeleton import measures as sk
    from s3o_warp.skeleton import mstep
    from s3o_warp.skeleton.mstep import joint_samples, m_step

    cfg, data, f, frames = joint_fitter(tiny_sequence, tmp_path)
    cfg.skeleton.t_o, cfg.skeleton.t_d, cfg.skeleton.t_u = 2.0, 1e9, float("inf")  # no merge, no joint: pruning only
    X, W = f.model.verts.detach().double().numpy(), f.model.skinning().detach().double().numpy()
    E = skj.bone_endpoints(X, W, f.skel.joints, t_r=cfg.skeleton.t_r, samples=joint_samples(f.model))
    L = sk.bone_lengths(E, X) / sk.size_of(X)
    inner = np.flatnonzero(np.bincount(f.skel.parents[f.skel.parents >= 0], minlength=len(L)) > 0)
    monkeypatch.setattr(mstep, "MIN_BONE_LENGTH", float(L[inner].min() * 1.001))  # the shortest inner bone is short
    # bones that own no vertex go too, whatever their length (prune_short_bones); the fit's state may hold some
    empty = np.bincount(sk.assign_parts(W), minlength=len(L))[: len(L)] == 0
    empty[inner[np.argmin(L[inner])]] = False
    before, loss0 = posed_and_loss(f, frames)
    B0 = f.model.num_bones
    assert m_step(f.model, f.opt, data, cfg, f.skel, cfg.skeleton.e1 + 1)
    B1 = B0 - 1 - int(empty.sum())
    assert f.model.num_bones == B1 and f.skel.history[-1]["operation"] == "prune"
    assert len(f.skel.parents) == B1 and (f.skel.parents == -1).sum() == 1
    after, loss1 = posed_and_loss(f, frames)
    assert_no_jump(before, after, loss0, loss1)  # measured: 0.08 % of the diagonal, 2.1 % of the loss (9 -> 8 bones)
    # 0 = the paper: nothing is pruned
    monkeypatch.setattr(mstep, "MIN_BONE_LENGTH", 0.0)
    assert not m_step(f.model, f.opt, data, cfg, f.skel, cfg.skeleton.e1 + 1)


def test_the_fits_end_merges_bones_that_own_no_vertex(tiny_sequence, tmp_path):
    """An inner bone that owns no vertex when the fit ends is merged into its parent
    (its child re-hangs there, a joint between them replaces its two), and the posed mesh and the loss stay."""
    from s3o_warp.skeleton.mstep import m_step

    cfg, data, f, frames = joint_fitter(tiny_sequence, tmp_path)
    assert m_step(f.model, f.opt, data, cfg, f.skel, cfg.skeleton.e1)  # upsampling: chains with inner bones
    P = f.skel.parents
    inner = [b for b in range(len(P)) if P[b] >= 0 and (P == b).any()]
    b = inner[0]
    before, loss0 = posed_and_loss(f, frames)
    with torch.no_grad():  # the bone's Gaussian moves far off: it owns nothing and weighs ~0 everywhere
        f.model.bone_centers[b] += 10.0 * (f.model.verts.amax(0) - f.model.verts.amin(0)).norm()
    assert (f.model.skinning().argmax(1) != b).all()
    B0, parent, kids = f.model.num_bones, int(P[b]), np.flatnonzero(P == b)
    f.final_skeleton()
    assert f.model.num_bones == B0 - 1 and f.skel.history[-1]["operation"] == "prune empty (end)"
    new = lambda x: x - (x > b)  # noqa: E731 - indices after b shift down by one
    assert [int(f.skel.parents[new(k)]) for k in kids] == [new(parent)] * len(kids)
    assert {(new(parent), new(int(k))) for k in kids} <= {tuple(j) for j in f.skel.joints.tolist()}
    after, loss1 = posed_and_loss(f, frames)  # as before the bone emptied (its regulariser aside)
    assert_no_jump(before, after, loss0, loss1)
    f.final_skeleton()  # nothing empty any more
    assert f.model.num_bones == B0 - 1


def test_m_step_does_not_merge_on_a_few_frames(tiny_sequence, tmp_path, caplog, monkeypatch):
    """A pair that agrees (> t_o) merges when compared on enough frame pairs, and is kept apart, with one log
    line, when mstep.MIN_FRAMES_FRACTION asks for more frame pairs than it was compared on."""
    from s3o_warp.skeleton import mstep
    from s3o_warp.skeleton.mstep import bone_motion_similarity, m_step, merge_min_frames

    cfg, data, f, frames = joint_fitter(tiny_sequence, tmp_path)
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
