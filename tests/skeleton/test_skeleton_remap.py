"""Applying an edit to the model (s3o_warp.skeleton.remap): no jump in the posed mesh or the loss, Adam state
carried over bit for bit for kept bones, exact re-pivoting of shifted and merged bones."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
import trimesh

from s3o_warp.geometry import axis_angle_to_matrix, matrix_to_quat
from s3o_warp.model import ModelInit, S3OModel
from s3o_warp.skeleton.edit import grow_skeleton, shift_bones, upsample_skeleton
from s3o_warp.skeleton.remap import apply_edit, remap_bones

# -------------------------------------------------------------------------------------------------
# model surgery
# -------------------------------------------------------------------------------------------------


def _model(seed=12, T=4, device="cpu"):
    """A capsule along x with two bones (left/right half), random small motion, the fit's Adam groups."""
    g = torch.Generator().manual_seed(seed)
    mesh = trimesh.creation.capsule(height=2.0, radius=0.3, count=[12, 12])
    R90 = trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0])
    mesh.apply_transform(R90)  # axis along x
    X = torch.tensor(mesh.vertices, dtype=torch.float32)
    centers = torch.tensor([[-0.6, 0, 0], [0.6, 0, 0]])
    init = ModelInit(
        verts=X, faces=torch.tensor(mesh.faces), colors=torch.full((len(X), 3), 0.5), centers=centers,
        rotations=torch.eye(3).expand(2, 3, 3).clone(), log_scales=torch.log(torch.tensor([[3.0, 8, 8]] * 2)),
        root_R=torch.eye(3).expand(T, 3, 3).clone(), root_t=torch.tensor([[0.0, 0, 4]] * T),
        focal=100.0, crop_scale=torch.ones(T), crop_size=64, crop_to_frame=torch.eye(3).expand(T, 3, 3).clone())
    m = S3OModel(init).to(device)
    with torch.no_grad():
        m.bone_aa.copy_(0.3 * torch.randn(T, 2, 3, generator=g))
        m.bone_t.copy_(0.1 * torch.randn(T, 2, 3, generator=g))
    target = (torch.randn(T, len(X), 3, generator=g) * 0.05).to(device)
    opt = torch.optim.Adam([
        {"params": [m.root_aa, m.root_t, m.bone_aa, m.bone_t], "lr": 1e-2, "name": "motion"},
        {"params": [m.verts, m.color_logits], "lr": 1e-3, "name": "shape"},
        {"params": [m.bone_centers, m.bone_quat, m.bone_log_scales], "lr": 1e-2, "name": "bones"},
    ])
    return m, opt, target


def _loss(m, target):
    frames = torch.arange(m.num_frames)
    return ((m.forward(frames) - m.forward(frames).detach().mean() - target) ** 2).mean()


def _steps(m, opt, target, n):
    for _ in range(n):
        opt.zero_grad()
        _loss(m, target).backward()
        opt.step()


def test_remap_split_keeps_posed_mesh_and_loss(device):
    m, opt, target = _model(device=device)
    _steps(m, opt, target, 3)
    frames = torch.arange(m.num_frames)
    with torch.no_grad():
        before = m.forward(frames)
        loss0 = float(_loss(m, target))
    X = m.verts.detach()
    W = m.skinning().detach()
    C, Q = m.bone_centers.detach(), m.precisions().detach()
    e = upsample_skeleton(X, W, C, Q, np.array([-1, 0]))
    assert e.num_bones == 4
    # baseline for "a jump": the same split with the new bones at rest (no inherited motion)
    m_rest = copy.deepcopy(m)
    apply_edit(m_rest, None, e)
    with torch.no_grad():
        m_rest.bone_aa.zero_()
        m_rest.bone_t.zero_()
        rest = m_rest.forward(frames)
    apply_edit(m, opt, e)
    assert m.num_bones == 4 and m.bone_aa.shape == (m.num_frames, 4, 3)
    assert all(getattr(m, n).device == before.device for n in ("bone_centers", "bone_quat", "bone_t"))
    with torch.no_grad():
        after = m.forward(frames)  # skinning weights recomputed from the new Gaussians
        loss1 = float(_loss(m, target))
    jump = (after - before).norm(dim=-1)
    rest_jump = (rest - before).norm(dim=-1)
    assert float(jump.mean()) < 0.05 * float(rest_jump.mean()) and float(jump.max()) < 0.25 * float(rest_jump.max())
    assert abs(loss1 - loss0) < 0.05 * loss0
    # every half inherits its parent's transform exactly: with the old weights split over the halves
    # (each half getting the part of the parent's weight it took), the blend is the parent's
    Wn = m.skinning().detach()
    W_half = torch.zeros_like(Wn)
    for j, src in enumerate(e.sources):
        i = src[0][0]
        den = sum(Wn[:, k] for k, s in enumerate(e.sources) if s[0][0] == i)
        share = torch.where(den > 0, Wn[:, j] / den.clamp_min(1e-30), torch.full_like(den, 0.5))
        W_half[:, j] = W[:, i] * share
    with torch.no_grad():
        exact = m.forward(frames, weights=W_half)
    torch.testing.assert_close(exact, before, atol=2e-5, rtol=0)
    # params and groups: the optimiser holds the new tensors, no stale ones
    held = {id(p) for g in opt.param_groups for p in g["params"]}
    for name in ("bone_centers", "bone_quat", "bone_log_scales", "bone_aa", "bone_t"):
        assert id(getattr(m, name)) in held
        assert getattr(m, name) in opt.state
    assert all(id(p) in held for p in opt.state)  # no state left on replaced tensors
    _steps(m, opt, target, 1)  # the optimiser still works


def test_remap_carries_adam_state_for_unchanged_bone():
    """Bone 0 is kept (new index 0), bone 1 is split: an Adam step on bone 0 equals the old optimiser's."""
    m, opt, target = _model(seed=13)
    _steps(m, opt, target, 4)
    X, W = m.verts.detach(), m.skinning().detach()
    C, Q = m.bone_centers.detach(), m.precisions().detach()
    e = upsample_skeleton(X, W, C, Q, np.array([-1, 0]), min_section_vertices=len(X))
    assert not e.changed
    # split only bone 1 (grow: it is a leaf; its reference extent is tiny)
    e = grow_skeleton(X, W, C, Q, np.array([-1, 0]), np.array([1e9, 1e-3]), sections=2)
    assert e.num_bones == 3 and e.kept.tolist() == [True, False, False]
    m_old, opt_old = copy.deepcopy((m, opt))
    old_state = {k: v.clone() for k, v in opt.state[m.bone_aa].items()}
    apply_edit(m, opt, e)
    # state mapped by the same sources: halves carry bone 1's moments exactly
    st = opt.state[m.bone_aa]
    for key in ("exp_avg", "exp_avg_sq"):
        assert torch.equal(st[key][:, 0], old_state[key][:, 0])
        assert torch.equal(st[key][:, 1], old_state[key][:, 1]) and torch.equal(st[key][:, 2], old_state[key][:, 1])
    assert torch.equal(st["step"], old_state["step"])

    def bone0_loss(mm):
        return ((mm.bone_aa[:, 0] - 0.1) ** 2).sum() + (mm.bone_t[:, 0] ** 3).sum() + \
            (mm.bone_centers[0] ** 2).sum() + mm.bone_log_scales[0].sum() + mm.bone_quat[0, 1]

    for mm, oo in ((m, opt), (m_old, opt_old)):
        oo.zero_grad()
        bone0_loss(mm).backward()
        oo.step()
    for name in ("bone_aa", "bone_t"):
        assert torch.equal(getattr(m, name)[:, 0], getattr(m_old, name)[:, 0])
    for name in ("bone_centers", "bone_log_scales", "bone_quat"):
        assert torch.equal(getattr(m, name)[0], getattr(m_old, name)[0])


def test_remap_repivots_shift_and_merge_exactly():
    """Shifted centres and a merge of two bones with the same motion: posed mesh unchanged for fixed weights."""
    m, opt, target = _model(seed=14)
    _steps(m, opt, target, 2)
    frames = torch.arange(m.num_frames)
    W = m.skinning().detach()
    with torch.no_grad():
        before = m.forward(frames, weights=W)
    C = shift_bones(m.verts.detach(), W, m.bone_centers.detach()) + np.array([0.1, -0.2, 0.05])
    remap_bones(m, opt, [[(0, 1.0)], [(1, 1.0)]], C, m.bone_quat, m.bone_log_scales)
    with torch.no_grad():
        torch.testing.assert_close(m.forward(frames, weights=W), before, atol=2e-5, rtol=0)
        # give both bones the same affine motion, then merge them with 30/70 weights
        R = axis_angle_to_matrix(m.bone_aa[:, 0])
        a = m.bone_centers[0] + m.bone_t[:, 0] - (R @ m.bone_centers[0][:, None])[..., 0]
        m.bone_aa[:, 1] = m.bone_aa[:, 0]
        m.bone_t[:, 1] = a - m.bone_centers[1] + (R @ m.bone_centers[1][:, None])[..., 0]
        before = m.forward(frames, weights=W)
    q = matrix_to_quat(torch.eye(3, dtype=torch.float64))[None]
    remap_bones(m, opt, [[(0, 0.3), (1, 0.7)]], torch.zeros(1, 3), q, torch.zeros(1, 3))
    with torch.no_grad():
        after = m.forward(frames, weights=W.sum(1, keepdim=True))
    torch.testing.assert_close(after, before, atol=2e-5, rtol=0)
    assert opt.state[m.bone_aa]["exp_avg"].shape == (m.num_frames, 1, 3)
    with pytest.raises(ValueError, match="weights must sum to 1"):
        remap_bones(m, opt, [[(0, 0.5)]], torch.zeros(1, 3), q, torch.zeros(1, 3))
    with pytest.raises(ValueError, match="must list old bones"):
        remap_bones(m, opt, [[(3, 1.0)]], torch.zeros(1, 3), q, torch.zeros(1, 3))
