"""What the M-step measures (s3o_warp.skeleton.measures): bone flow (eq. 4) against a cv2.remap twin, motion
similarity (eq. 8) against a naive twin, unexplained motion, length variation (eq. 6), the kinematic tree and
skeleton.json."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
from skeleton_cases import chain, flow_field, hard_weights

from s3o_warp.geometry import project
from s3o_warp.skeleton.edit import shift_bones
from s3o_warp.skeleton.joints import bone_endpoints, bone_halves
from s3o_warp.skeleton.measures import (
    bone_flow,
    create_joints,
    kinematic_tree,
    motion_similarity,
    skeleton_json,
    tree_joints,
    unexplained_motion,
)

# -------------------------------------------------------------------------------------------------
# bone_flow (eq. 4)
# -------------------------------------------------------------------------------------------------


def _bone_flow_naive(verts_cam, K, flow, visible, W, min_visible, min_mass):
    """Per-vertex cv2.remap bilinear sampling (pixel centres at integers) and explicit sums."""
    T, N = verts_cam.shape[:2]
    S = flow.shape[1]
    uv = project(torch.as_tensor(verts_cam), torch.as_tensor(K)).numpy()
    F = np.zeros((T - 1, W.shape[1], 2))
    ok = np.zeros((T - 1, W.shape[1]), bool)
    for t in range(T - 1):
        mx = uv[t, :, 0].astype(np.float32)[None]
        my = uv[t, :, 1].astype(np.float32)[None]
        f = cv2.remap(flow[t], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]
        inside = (mx[0] >= -0.5) & (mx[0] <= S - 0.5) & (my[0] >= -0.5) & (my[0] <= S - 0.5)
        v = (visible[t] & inside).astype(np.float64)
        for b in range(W.shape[1]):
            m = (W[:, b] * v).sum()
            if m >= min_visible * W[:, b].sum() and m >= min_mass and m > 0:
                ok[t, b] = True
                F[t, b] = (W[:, b, None] * v[:, None] * f).sum(0) / m
    return F, ok


def _two_parts(rng, N, x_max, y_max):
    """``(N, 3)`` points at depth 2: the first half at x in [-x_max, -0.1], the second at [0.1, x_max]."""
    X = np.zeros((N, 3))
    X[: N // 2, 0] = rng.uniform(-x_max, -0.1, N // 2)
    X[N // 2:, 0] = rng.uniform(0.1, x_max, N - N // 2)
    X[:, 1] = rng.uniform(-y_max, y_max, N)
    X[:, 2] = 2.0
    return X


def test_bone_flow_two_translating_parts_one_hidden():
    """Bone 0 on the left half (flow (+2, 1)), bone 1 on the right (flow (-3, 0)); hidden verts are ignored."""
    rng = np.random.default_rng(1)
    S, T, N = 64, 3, 200
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 31.5], [0, 0, 1]])
    # vertices at depth 2: left part x in [-0.55, -0.1] -> cols ~ [18, 29]; right part x in [0.1, 0.55]
    verts = np.repeat(_two_parts(rng, N, 0.55, 0.4)[None], T, 0)
    flow = flow_field(T - 1, S, lambda c, r, t: (np.where(c < 31.5, 2.0, -3.0), np.where(c < 31.5, 1.0, 0.0)))
    # hidden: 20 of bone 0's vertices are moved into the right half (wrong flow) but marked hidden
    verts[0, :20, 0] = 0.4
    visible = np.ones((T, N), bool)
    visible[0, :20] = False
    visible[1, 100:] = False  # bone 1 fully hidden in frame 1
    labels = np.r_[np.zeros(100, int), np.ones(100, int)]
    W = hard_weights(labels, 2)
    F, ok = bone_flow(torch.tensor(verts, dtype=torch.float32), torch.tensor(K).float().expand(T, 3, 3),
                         torch.tensor(flow), torch.tensor(visible), torch.tensor(W, dtype=torch.float32))
    torch.testing.assert_close(F[0], torch.tensor([[2.0, 1.0], [-3.0, 0.0]]), atol=1e-5, rtol=0)
    torch.testing.assert_close(F[1, 0], torch.tensor([2.0, 1.0]), atol=1e-5, rtol=0)
    assert ok.tolist() == [[True, True], [True, False]]
    assert F[1, 1].abs().max() == 0


def test_bone_flow_blends_the_fitted_motion_like_the_observed():
    """``predicted``: the fitted per-vertex motion is blended with the same weights and visibility as the flow."""
    rng = np.random.default_rng(4)
    S, T, N = 64, 3, 200
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 31.5], [0, 0, 1]])
    verts = np.repeat(_two_parts(rng, N, 0.55, 0.4)[None], T, 0)
    flow = flow_field(T - 1, S, lambda c, r, t: (np.where(c < 31.5, 2.0, -3.0), np.zeros_like(c)))
    visible = np.ones((T, N), bool)
    visible[0, :20] = False
    pred = np.zeros((T - 1, N, 2), np.float32)
    pred[:, :100] = [5.0, 0.0]
    pred[:, 100:] = [0.0, 5.0]
    pred[0, :20] = [100.0, 100.0]  # hidden in frame 0: not blended
    W = torch.tensor(hard_weights(np.r_[np.zeros(100, int), np.ones(100, int)], 2), dtype=torch.float32)
    args = (torch.tensor(verts, dtype=torch.float32), torch.tensor(K).float().expand(T, 3, 3), torch.tensor(flow),
            torch.tensor(visible), W)
    F, ok, G = bone_flow(*args, predicted=torch.tensor(pred))
    F0, ok0 = bone_flow(*args)
    torch.testing.assert_close(F, F0)
    torch.testing.assert_close(G, torch.tensor([[[5.0, 0.0], [0.0, 5.0]]] * 2), atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="predicted"):
        bone_flow(*args, predicted=torch.tensor(pred[:1]))


def test_bone_flow_matches_cv2_remap_twin(device):
    """Smooth random flow, soft weights, random visibility and a vertex off the image: against cv2.remap sums."""
    rng = np.random.default_rng(2)
    S, T, N, B = 40, 4, 150, 3
    K = np.array([[40.0, 0, 19.5], [0, 40.0, 19.5], [0, 0, 1]])
    verts = np.concatenate([rng.uniform(-0.45, 0.45, (T, N, 2)), rng.uniform(1.8, 2.2, (T, N, 1))], -1)
    verts[0, 0, 0] = 5.0  # projects far outside: dropped
    flow = flow_field(T - 1, S, lambda c, r, t: (np.sin(c / 5 + t) * 3, np.cos(r / 7) * 2 + c / 20))
    visible = rng.uniform(size=(T, N)) > 0.3
    W = rng.dirichlet(np.ones(B) * 0.5, N)
    kw = dict(min_visible=0.2, min_mass=3.0)
    F, ok = bone_flow(*(torch.tensor(a).to(device) for a in (verts.astype(np.float32), np.broadcast_to(
        K, (T, 3, 3)).astype(np.float32), flow, visible, W.astype(np.float32))), **kw)
    assert F.device.type == torch.device(device).type
    F, ok = F.cpu(), ok.cpu()
    Fr, okr = _bone_flow_naive(verts.astype(np.float32), np.broadcast_to(K, (T, 3, 3)).astype(np.float32), flow,
                               visible, W, **kw)
    assert ok.numpy().tolist() == okr.tolist()
    np.testing.assert_allclose(F.numpy(), Fr, atol=2e-3)


def test_bone_flow_barely_visible_is_invalid():
    N, T = 50, 2
    verts = torch.zeros(T, N, 3)
    verts[..., 2] = 1
    K = torch.tensor([[10.0, 0, 4.5], [0, 10.0, 4.5], [0, 0, 1]]).expand(T, 3, 3)
    flow = torch.ones(1, 10, 10, 2)
    W = torch.zeros(N, 2)
    W[:, 0] = 1
    W[:10, 0], W[:10, 1] = 0, 1
    vis = torch.ones(T, N, dtype=torch.bool)
    vis[0, :9] = False  # 1 of bone 1's 10 vertices seen: 10% of its mass but below min_mass=3
    F, ok = bone_flow(verts, K, flow, vis, W)
    assert ok[0].tolist() == [True, False]
    F, ok = bone_flow(verts, K, flow, vis, W, min_mass=1.0, min_visible=0.05)
    assert ok[0].tolist() == [True, True]
    with pytest.raises(ValueError, match="flow must have shape"):
        bone_flow(verts, K, flow[0], vis, W)


# -------------------------------------------------------------------------------------------------
# motion similarity (eq. 8)
# -------------------------------------------------------------------------------------------------


def _similarity_naive(F, valid, m, min_frames):
    T1, B = valid.shape
    out = np.full((B, B), -np.inf)
    for a in range(B):
        for b in range(B):
            vals = []
            for t in range(T1):
                fa, fb = F[t, a], F[t, b]
                na, nb = np.linalg.norm(fa), np.linalg.norm(fb)
                if valid[t, a] and valid[t, b] and (na >= m or nb >= m):
                    vals.append(fa @ fb / (max(na, m) * max(nb, m)))
            if len(vals) >= min_frames:
                out[a, b] = min(vals)
        out[a, a] = 1
    return out


def test_motion_similarity_together_vs_different_and_static_frames():
    rng = np.random.default_rng(3)
    T1 = 8
    d = rng.normal(size=(T1, 2)) * 4
    F = np.zeros((T1, 4, 2))
    F[:, 0] = d
    F[:, 1] = 0.5 * d + rng.normal(0, 0.02, (T1, 2))  # same direction, slower: moves together
    F[:, 2] = d @ np.array([[0, 1], [-1, 0]])  # perpendicular: different motion
    F[:, 3] = d
    F[2, :2] = 0.01  # a static frame for bones 0 and 1: skipped, not a disagreement
    valid = np.ones((T1, 4), bool)
    valid[1:, 3] = False  # bone 3 seen in one frame only
    Sim = motion_similarity(torch.tensor(F).float(), torch.tensor(valid))
    assert Sim[0, 1] > 0.99 and Sim[1, 0] == Sim[0, 1]
    assert Sim[0, 2] < 0.1
    assert Sim[0, 3] == -np.inf
    np.testing.assert_allclose(Sim.numpy(), _similarity_naive(F, valid, 0.5, 2), atol=1e-5)
    # a frame where only one of the pair moves drives the similarity towards 0
    F2 = F.copy()
    F2[4, 1] = 0
    assert motion_similarity(torch.tensor(F2).float(), torch.tensor(valid))[0, 1] < 0.05


def test_motion_similarity_is_the_minimum_over_frames():
    """Eq. 8 "in every frame": one frame where two bones that otherwise move together disagree vetoes the pair."""
    rng = np.random.default_rng(5)
    T1 = 20
    d = rng.normal(size=(T1, 2)) * 3
    F = np.stack([d, d + rng.normal(0, 0.05, (T1, 2)), -d], 1)  # 0 and 1 together, 2 opposite
    F[7, 1] = -F[7, 0]  # one frame of flow noise
    valid = np.ones((T1, 3), bool)
    valid[:3, 2] = False
    Sim = motion_similarity(torch.tensor(F).float(), torch.tensor(valid))
    np.testing.assert_allclose(Sim.numpy(), _similarity_naive(F, valid, 0.5, 2), atol=1e-5)
    assert Sim[0, 1] < -0.9 and Sim[0, 2] < -0.99


# -------------------------------------------------------------------------------------------------
# unexplained motion
# -------------------------------------------------------------------------------------------------


def _bending_end_part(bend: bool, T: int = 5):
    """The chain seen side on (x right, y down, depth 4), its end bone (x in [2, 3]) turning about the joint at
    x = 2 in the image plane, 0.1 rad per frame; with ``bend`` its far half (x > 2.5) turns twice as fast
    about x = 2.5 in the video (a knee inside the part). Returns the arguments of :func:`bone_flow`, with
    the fitted motion (``predicted``) the rigid turn."""
    X, W = chain()
    X = X - np.array([1.5, 0, -4.0])  # x in [-1.5, 1.5] at depth 4
    S, f = 96, 30.0
    K = np.array([[f, 0, 47.5], [0, f, 47.5], [0, 0, 1]])
    verts = np.repeat(X[None], T, 0)
    c, r = np.meshgrid(np.arange(S, dtype=float), np.arange(S, dtype=float))
    xw, yw = (c - 47.5) / f * 4.0, (r - 47.5) / f * 4.0  # the image back on the plane at depth 4
    j, k = 0.5, 1.0  # the joint and the knee in x

    def turn(x, y, cx, a):  # in-plane rotation by a about (cx, 0): the displacement
        return (np.cos(a) - 1) * (x - cx) - np.sin(a) * y, np.sin(a) * (x - cx) + (np.cos(a) - 1) * y

    def field(x, y):
        dx, dy = turn(x, y, j, 0.1)
        if bend:  # beyond the knee: the rigid turn plus a turn about the knee
            ex, ey = turn(x + dx, y + dy, j + (np.cos(0.1) - 1) * (k - j), 0.1)
            far = x > k
            dx, dy = np.where(far, dx + ex, dx), np.where(far, dy + ey, dy)
        return np.where(x > j, dx, 0.0) * f / 4.0, np.where(x > j, dy, 0.0) * f / 4.0

    flow = flow_field(T - 1, S, lambda cc, rr, t: field(xw, yw))
    dx, dy = turn(X[:, 0], X[:, 1], j, 0.1)
    pred = np.stack([np.where(X[:, 0] > j, dx, 0.0), np.where(X[:, 0] > j, dy, 0.0)], -1) * f / 4.0
    pred = np.repeat(pred[None], T - 1, 0).astype(np.float32)
    args = (torch.tensor(verts, dtype=torch.float32), torch.tensor(K).float().expand(T, 3, 3), torch.tensor(flow),
            torch.ones(T, len(X), dtype=torch.bool))
    return X + np.array([1.5, 0, -4.0]), W, args, torch.tensor(pred)


@pytest.mark.parametrize("bend", [False, True])
def test_unexplained_motion_finds_a_knee_inside_an_end_bone(bend):
    """A rigid turn that the fit reproduces leaves almost nothing unexplained; a knee inside the part, which the
    one rigid bone cannot follow, leaves the halves' extra relative motion unexplained (measured: 0.007 and 0.58;
    the fit turns the part as a whole, the video's far half turns twice as much)."""
    X, W, args, pred = _bending_end_part(bend)
    P = np.array([-1, 0, 1])
    E = bone_endpoints(X, W, tree_joints(P))
    bones, W2 = bone_halves(X, W, shift_bones(X, W, np.zeros((3, 3))), P, E, np.array([False, False, True]))
    F, ok, G = bone_flow(*args, torch.tensor(W2, dtype=torch.float32), predicted=pred)
    assert ok.all()
    r, n = unexplained_motion(F, G, ok, [[0, 1]], min_flow=0.1)
    assert n.tolist() == [4]
    if bend:
        assert r[0] > 0.4
    else:
        assert r[0] < 0.05


def test_unexplained_motion_values_and_frames():
    """r = |o - g| / max(|o|, |g|) per frame, its median; both under min_flow: 0; too few frames: NaN."""
    F = torch.zeros(4, 4, 2)
    G = torch.zeros(4, 4, 2)
    F[:, 1] = torch.tensor([2.0, 0.0])   # pair (0, 1): observed relative motion (2, 0) ...
    G[:, 1] = torch.tensor([[2.0, 0.0], [1.0, 0.0], [0.0, 0.0], [-2.0, 0.0]])  # ... fitted: r = 0, .5, 1, 2
    F[:, 3] = torch.tensor([0.1, 0.0])   # pair (2, 3): both barely move
    G[:, 3] = torch.tensor([-0.1, 0.0])
    ok = torch.ones(4, 4, dtype=torch.bool)
    r, n = unexplained_motion(F, G, ok, [[0, 1], [2, 3]], min_flow=0.5)
    np.testing.assert_allclose(r, [0.75, 0.0])
    assert n.tolist() == [4, 4]
    ok[1:, 0] = False
    r, n = unexplained_motion(F, G, ok, [[0, 1], [2, 3]], min_flow=0.5, min_frames=2)
    assert np.isnan(r[0]) and n.tolist() == [1, 4]
    with pytest.raises(ValueError, match="pairs"):
        unexplained_motion(F, G, ok, [[0, 4]])


# -------------------------------------------------------------------------------------------------
# length variation (eq. 6)
# -------------------------------------------------------------------------------------------------


def test_create_joints_leaves_no_half_shorter_than_min_length():
    """A bone stretching by 50 % gets a joint unless its halves would be shorter than min_length."""
    L = np.stack([np.array([1.0, 0.1 * (1 + 0.5 * f / 5), 1.0]) for f in range(6)])  # bone 1: median 0.125
    assert create_joints(L).tolist() == [False, True, False]  # the paper's relative test alone
    assert create_joints(L, min_length=0.06).tolist() == [False, True, False]  # halves 0.0625 >= 0.06
    assert not create_joints(L, min_length=0.07).any()  # halves would be 0.0625 < 0.07


# -------------------------------------------------------------------------------------------------
# kinematic tree, skeleton.json
# -------------------------------------------------------------------------------------------------


def _is_tree(parents):
    B = len(parents)
    roots = [b for b in range(B) if parents[b] == -1]
    if len(roots) != 1:
        return False
    for b in range(B):
        seen, a = set(), b
        while a != -1:
            if a in seen:
                return False
            seen.add(a)
            a = int(parents[a])
    return True


def test_kinematic_tree_is_a_spanning_tree():
    # a cycle 0-1-2-0, a chain 2-3, bone 4 without joints (nearest centre: bone 3), bone 5 joined to 4
    joints = np.array([[0, 1], [1, 2], [2, 0], [2, 3], [4, 5]])
    C = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [2, 1, 0], [3, 1.2, 0], [4, 1, 0]], float)
    W = hard_weights(np.r_[np.ones(5, int), np.zeros(3, int), np.arange(6)], 6)
    p = kinematic_tree(6, joints, weights=W, centers=C)
    assert _is_tree(p) and p[1] == -1  # the root is the bone with the most vertices
    assert p[4] == 3 and p[5] == 4
    assert p[0] == 1 and p[2] == 1 and p[3] == 2
    p0 = kinematic_tree(6, joints, root=5)
    assert _is_tree(p0) and p0[5] == -1
    with pytest.raises(ValueError, match="joints must index"):
        kinematic_tree(3, [[0, 3]])


def test_skeleton_json_shapes():
    C = np.arange(6.0).reshape(2, 3)
    Q = np.stack([np.eye(3), 2 * np.eye(3)])
    d = skeleton_json(C, Q, [1.0, 2.0], [-1, 0], [[0, 1]], [[0.5, 0.5, 0.5]])
    d = json.loads(json.dumps(d))
    assert [len(r) for r in d["B"]] == [13, 13] and [len(r) for r in d["J"]] == [5]
    assert d["B"][1][:3] == [3, 4, 5] and d["B"][1][3] == 2 and d["B"][1][-1] == 2
    assert d["J"][0] == [0, 1, 0.5, 0.5, 0.5] and d["root"] == 0 and d["parents"] == [-1, 0]
    with pytest.raises(ValueError, match="precisions must have shape"):
        skeleton_json(C, Q[:1], [1.0, 2.0], [-1, 0], [], [])
