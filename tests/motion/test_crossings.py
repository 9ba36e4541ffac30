"""Paired limbs through their crossings (s3o_warp.motion.crossings): labelling, exchanged motion, in place."""

import numpy as np
import pytest
import torch
from conftest import smoke_config

from s3o_warp.geometry import axis_angle_to_matrix, matrix_to_axis_angle
from s3o_warp.motion.crossings import (
    LimbPair,
    crossing_labels,
    exchange_costs,
    exchanged_motion,
    resolve_crossings,
)

S = np.diag([1.0, 1.0, -1.0])


def test_exchange_costs_against_loops():
    """Naive twin: velocities over k frames before t and after t+1, along the same or the other path."""
    rng = np.random.default_rng(0)
    T, k = 12, 3
    pa, pb = rng.normal(size=(T, 2)), rng.normal(size=(T, 2))
    stay, swap = exchange_costs(pa, pb, k)
    for t in range(T - 1):
        if t - k < 0 or t + 1 + k > T - 1:
            assert np.isinf(stay[t]) and np.isinf(swap[t])
            continue
        v = {n: ((p[t] - p[t - k]) / k, (p[t + 1 + k] - p[t + 1]) / k) for n, p in (("a", pa), ("b", pb))}
        st = np.sum((v["a"][1] - v["a"][0]) ** 2) + np.sum((v["b"][1] - v["b"][0]) ** 2)
        sw = np.sum((v["b"][1] - v["a"][0]) ** 2) + np.sum((v["a"][1] - v["b"][0]) ** 2)
        assert stay[t] == pytest.approx(st) and swap[t] == pytest.approx(sw)
    stay, swap = exchange_costs(pa[:7], pb[:7], k)  # too short for a window on both sides
    assert np.isinf(stay).all() and np.isinf(swap).all() and len(stay) == 6


def test_bouncing_feet_swing_through():
    """Two feet swing past each other; the fit kept one always in front (a bounce at each crossing)."""
    t = np.arange(30, dtype=np.float64)
    f1 = 0.3 * np.sin(0.35 * t + 0.5)
    f2 = -f1 + 0.01  # they cross four times
    front, back = np.maximum(f1, f2), np.minimum(f1, f2)
    pa, pb = np.stack([front, 0 * t], 1), np.stack([back, 0 * t], 1)
    s = crossing_labels(pa, pb, anchor=4, max_gap=0.15)  # sampled at 0.2 per frame apart
    fixed_a = np.where(s, pb[:, 0], pa[:, 0])
    truth = f1 if abs(f1[4] - pa[4, 0]) < 1e-12 else f2
    assert np.allclose(fixed_a, truth)
    # no crossing, nothing to exchange
    assert not crossing_labels(np.stack([f1 + 2, 0 * t], 1), pb, anchor=4, max_gap=0.15).any()
    # the fit's bounce seldom touches: a gap at the crossing is bridged when allowed, not beyond max_gap
    gap = np.array([0.05, 0.0])
    assert s.any() and not s[4]
    assert np.array_equal(crossing_labels(pa + gap, pb, anchor=4, max_gap=0.25), s)
    assert not crossing_labels(pa + gap, pb, anchor=4, max_gap=0.04).any()


def _rand_rot(rng, n):
    return axis_angle_to_matrix(torch.as_tensor(rng.normal(size=(n, 3)) * 0.6)).numpy()


@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (1.0, 0.0, 0.0)])
def test_exchanged_motion_mirrors_partner(normal):
    """Through the side view's plane z = 0 (the default) and a front view's x = 0 (``LimbPair.mirror``)."""
    pair = LimbPair(0, 1, *(np.zeros(3),) * 4, normal=normal)
    S = pair.mirror
    np.testing.assert_allclose(S, np.eye(3) - 2 * np.outer(normal, normal))
    mirror = None if normal[2] else S
    rng = np.random.default_rng(0)
    T = 5
    top_a, end_a = np.array([0.1, 0.0, -0.1]), np.array([0.3, 0.5, -0.1])
    top_b, end_b = np.array([0.1, 0.0, 0.1]), np.array([-0.2, 0.55, 0.1])  # another rest angle and length
    A_b, b_b = _rand_rot(rng, T), rng.normal(size=(T, 3))
    c_a = np.array([0.2, 0.25, -0.1])
    R, t = exchanged_motion(A_b, b_b, top_a, end_a, top_b, end_b, c_a, mirror)
    assert np.allclose(np.linalg.det(R), 1) and np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-12)

    def posed_a(x):
        return np.einsum("tij,j->ti", R, x - c_a) + c_a + t

    # a's top lands on b's posed top reflected; a's axis points along b's posed axis reflected
    want_top = (np.einsum("tij,j->ti", A_b, top_b) + b_b) @ S.T
    assert np.allclose(posed_a(top_a), want_top)
    d_b = np.einsum("tij,j->ti", A_b, end_b - top_b) @ S.T
    d_a = posed_a(end_a) - posed_a(top_a)
    cos = (d_a * d_b).sum(1) / np.linalg.norm(d_a, axis=1) / np.linalg.norm(d_b, axis=1)
    assert np.allclose(cos, 1)
    # mirror-image rests: the whole limb is the partner's reflection
    R2, t2 = exchanged_motion(A_b, b_b, S @ top_b, S @ end_b, top_b, end_b, c_a, mirror)
    x = rng.normal(size=3)
    got = np.einsum("tij,j->ti", R2, x - c_a) + c_a + t2
    assert np.allclose(got, (np.einsum("tij,j->ti", A_b, S @ x) + b_b) @ S.T)


def _side_view(P):
    """A camera looking along z, 100 px per unit: object-frame points (T, 3) -> pixels (T, 2)."""
    return 100.0 * np.asarray(P)[:, :2]


def test_resolve_crossings_in_place():
    """Two one-bone legs hanging from a hip, bouncing: after the call they swing through, and the
    frames where nothing changes keep their parameters bit for bit."""
    T = 21  # crossings near frames 7 and 15, none at the ends
    top_a, top_b = np.array([0.0, 0.0, -0.1]), np.array([0.0, 0.0, 0.1])
    end_a, end_b = np.array([0.0, 0.5, -0.1]), np.array([0.0, 0.5, 0.1])
    centres = torch.tensor([[0.0, -0.3, 0.0], [0.0, 0.25, -0.1], [0.0, 0.25, 0.1]], dtype=torch.float64)
    tt = np.arange(T)
    ang1 = 0.5 * np.sin(0.4 * tt + 0.3)
    ang2 = -ang1
    front, back = np.maximum(ang1, ang2), np.minimum(ang1, ang2)  # the bounce: a always in front
    bone_aa = torch.zeros(T, 3, 3, dtype=torch.float64)
    bone_t = torch.zeros(T, 3, 3, dtype=torch.float64)
    for k, ang, top in ((1, front, top_a), (2, back, top_b)):
        aa = torch.zeros(T, 3, dtype=torch.float64)
        aa[:, 2] = -torch.as_tensor(ang)  # swing about z through the hip (forward = +x at the foot)
        R = axis_angle_to_matrix(aa).numpy()
        c = centres[k].numpy()
        bone_aa[:, k] = aa
        bone_t[:, k] = torch.as_tensor(top - c - np.einsum("tij,j->ti", R, top - c))  # hip fixed
    pair = LimbPair(a=1, b=2, top_a=top_a, end_a=end_a, top_b=top_b, end_b=end_b)
    before_aa, before_t = bone_aa.clone(), bone_t.clone()
    counts = resolve_crossings(bone_aa, bone_t, centres, [pair], anchor=2, project=_side_view, max_gap=0.6)
    assert counts[0] > 0
    R = axis_angle_to_matrix(bone_aa[:, 1]).numpy()
    foot = np.einsum("tij,j->ti", R, end_a - centres[1].numpy()) + centres[1].numpy() + bone_t[:, 1].numpy()
    hip = np.einsum("tij,j->ti", R, top_a - centres[1].numpy()) + centres[1].numpy() + bone_t[:, 1].numpy()
    assert np.allclose(hip, top_a, atol=1e-9)  # still attached
    x = foot[:, 0]
    truth = 0.5 * np.sin(ang1 if front[2] == ang1[2] else ang2)
    assert np.allclose(x, truth, atol=1e-9)
    same = torch.isclose(bone_aa[:, 1], before_aa[:, 1]).all(1).numpy()
    assert same[2] and not same.all()
    assert torch.equal(bone_aa[:, 0], before_aa[:, 0]) and torch.equal(bone_t[:, 0], before_t[:, 0])
    # axis-angle round trip used in place keeps rotations proper
    assert torch.allclose(axis_angle_to_matrix(matrix_to_axis_angle(axis_angle_to_matrix(bone_aa[:, 2]))),
                          axis_angle_to_matrix(bone_aa[:, 2]), atol=1e-9)



def test_resolve_crossings_in_the_image_where_depth_hides_the_crossing():
    """The bouncing legs of test_resolve_crossings_in_place, with leg b also pushed back in depth by two leg
    lengths: in 3D the feet never meet; seen along depth (``project``) they cross, and the step makes them swing
    through."""
    T = 21
    top_a, top_b = np.array([0.0, 0.0, -0.1]), np.array([0.0, 0.0, 0.1])
    end_a, end_b = np.array([0.0, 0.5, -0.1]), np.array([0.0, 0.5, 0.1])
    centres = torch.tensor([[0.0, -0.3, 0.0], [0.0, 0.25, -0.1], [0.0, 0.25, 0.1]], dtype=torch.float64)
    tt = np.arange(T)
    ang1 = 0.5 * np.sin(0.4 * tt + 0.3)
    front, back = np.maximum(ang1, -ang1), np.minimum(ang1, -ang1)

    def legs():
        bone_aa = torch.zeros(T, 3, 3, dtype=torch.float64)
        bone_t = torch.zeros(T, 3, 3, dtype=torch.float64)
        for k, ang, top, dz in ((1, front, top_a, 0.0), (2, back, top_b, 1.0)):
            aa = torch.zeros(T, 3, dtype=torch.float64)
            aa[:, 2] = -torch.as_tensor(ang)
            R = axis_angle_to_matrix(aa).numpy()
            c = centres[k].numpy()
            bone_aa[:, k] = aa
            bone_t[:, k] = torch.as_tensor(top - c - np.einsum("tij,j->ti", R, top - c) + [0.0, 0.0, dz])
        return bone_aa, bone_t

    bone_aa, bone_t = legs()
    seen = []

    def project(P):
        seen.append(P.shape)
        return _side_view(P)

    counts = resolve_crossings(bone_aa, bone_t, centres, [LimbPair(1, 2, top_a, end_a, top_b, end_b)], anchor=2,
                               max_gap=0.6, project=project)
    assert counts[0] > 0 and seen and all(s == (T, 3) for s in seen)
    R = axis_angle_to_matrix(bone_aa[:, 1]).numpy()
    foot = np.einsum("tij,j->ti", R, end_a - centres[1].numpy()) + centres[1].numpy() + bone_t[:, 1].numpy()
    truth = 0.5 * np.sin(ang1 if front[2] == ang1[2] else -ang1)
    assert np.allclose(foot[:, 0], truth, atol=1e-9)  # leg a swings through, frame by frame


def test_fit_projects_the_crossing_paths_like_the_model(tiny_sequence, tmp_path, monkeypatch):
    """The fit hands the step a projection equal to the model's full-frame one."""
    import s3o_warp.motion.crossings as X
    from s3o_warp.coarse.model import coarse_model
    from s3o_warp.data.store import prepare_data
    from s3o_warp.fit import Fitter

    cfg = _cfg()
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    fitter = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    got = {}

    def fake(bone_aa, bone_t, centres, pairs, anchor, *a, project=None):
        got["project"] = project
        return [0] * len(pairs)

    monkeypatch.setattr(X, "resolve_crossings", fake)
    fitter.resolve_crossings()
    m = fitter.model
    fr = torch.arange(m.num_frames)
    with torch.no_grad():
        obj = m.posed_object(fr)[:, 0].double().numpy()
        cam = m(fr)[:, 0]
        q = (m.intrinsics_frame(fr) @ cam[..., None])[..., 0]
        want = (q[:, :2] / q[:, 2:]).numpy()
    assert np.allclose(got["project"](obj), want, atol=1e-3)

# -- in the fit ---------------------------------------------------------------------------------------


_cfg = smoke_config  # tiny_sequence: conftest.py


def test_lift_gives_mirrored_limb_pairs(tiny_sequence, tmp_path):
    from s3o_warp.coarse.model import coarse_model
    from s3o_warp.data.store import prepare_data

    cfg = _cfg()
    res = coarse_model(prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu")), cfg)
    assert len(res.limb_pairs) >= 1
    for p in res.limb_pairs:
        assert p.a != p.b and max(p.a, p.b) < len(res.parents)
        assert res.parents[p.a] == res.parents[p.b]  # both hang from the same junction
        assert np.allclose(p.top_a[:2], p.top_b[:2]) and p.top_a[2] < 0 < p.top_b[2]  # mirrored tops
        assert np.linalg.norm(p.end_a - p.top_a) > 0 and np.linalg.norm(p.end_b - p.top_b) > 0


def test_fit_relabels_after_warmup_and_first_epoch_and_resets_moments(tiny_sequence, tmp_path, monkeypatch):
    """The pass runs at the warm-up's end and again before the first M-step; Adam's moments of the rewritten
    frames start afresh, the others are kept."""
    import json

    import s3o_warp.motion.crossings as X
    from s3o_warp.coarse.model import coarse_model
    from s3o_warp.data.store import prepare_data
    from s3o_warp.fit import Fitter

    cfg = _cfg(**{"coarse.steps": 5, "motion.warmup_steps": 5, "motion.steps": 8, "skeleton.epochs": 2,
                  "motion.resolve_crossings": True, "motion.hypotheses": 1})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    fitter = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    calls = []

    def fake(bone_aa, bone_t, centres, pairs, anchor, *a, **kw):
        calls.append((fitter.phase, fitter.step))
        if fitter.phase == "joint" and fitter.step > 0:
            st = fitter.opt.state[fitter.model.bone_aa]
            assert st["exp_avg_sq"].abs().sum() > 0
            bone_aa.data[2, pairs[0].a] += 0.1  # one frame of one bone rewritten
        return [1] + [0] * (len(pairs) - 1)

    monkeypatch.setattr(X, "resolve_crossings", fake)
    fitter.run()
    assert [c for c in calls if isinstance(c, tuple)] == [("warmup", 5), ("joint", 4)]
    log = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log if r.get("what") == "crossings"] == [5, 4]  # warm-up step 5, joint step 4


def test_moments_of_rewritten_frames_are_reset(tiny_sequence, tmp_path, monkeypatch):
    import s3o_warp.motion.crossings as X
    from s3o_warp.coarse.model import coarse_model
    from s3o_warp.data.store import prepare_data
    from s3o_warp.fit import Fitter

    cfg = _cfg(**{"motion.resolve_crossings": True})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    fitter = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    m = fitter.model
    fitter.phase = "joint"
    fitter.opt = fitter.make_optimizer()
    for p in (m.bone_aa, m.bone_t):  # some optimiser state
        p.grad = torch.ones_like(p)
    fitter.opt.step()
    a = fitter.coarse.limb_pairs[0].a
    before = {k: v.clone() for k, v in fitter.opt.state[m.bone_aa].items()}

    def fake(bone_aa, bone_t, centres, pairs, anchor, *args, **kw):
        bone_aa.data[2, a] += 0.1
        return [1]

    monkeypatch.setattr(X, "resolve_crossings", fake)
    fitter.resolve_crossings()
    st = fitter.opt.state[m.bone_aa]
    for key in ("exp_avg", "exp_avg_sq"):
        assert (st[key][2, a] == 0).all()
        mask = torch.ones(st[key].shape[:2], dtype=torch.bool)
        mask[2, a] = False
        assert torch.equal(st[key][mask], before[key][mask])
