"""The E-step objective's terms (motion/objective.py, motion/losses.py) against dense twins, and their weights."""

from __future__ import annotations

import pytest
import torch
from conftest import smoke_config

from s3o_warp.coarse.model import coarse_model
from s3o_warp.data.store import prepare_data
from s3o_warp.fit import Fitter

_cfg = smoke_config  # tiny_sequence: conftest.py


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


def test_coverage_term_follows_its_weight_and_pulls_the_bones(tiny_sequence, tmp_path, monkeypatch):
    """motion.w_cover adds the coverage term in both phases (0: none) and its gradient reaches the motion."""
    from s3o_warp.kernels.raster import rasterize

    import s3o_warp.motion.objective as O
    from s3o_warp.geometry import project
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
    from s3o_warp.geometry import axis_angle_to_matrix
    from s3o_warp.motion import losses as L

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
