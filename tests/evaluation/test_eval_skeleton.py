"""Skeleton scores (s3o_warp.evaluation.skeleton): joint distance against loops, limb and chain coverage and limb
identity on hand-made trees, joints inside a moving box, bones that own no vertex."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from s3o_warp.evaluation.shape import Similarity
from s3o_warp.evaluation.skeleton import (
    empty_bones,
    gt_limbs,
    joints_inside,
    limb_coverage,
    limb_identity,
    skeleton_distance,
)


def test_skeleton_distance_against_loops():
    rng = np.random.default_rng(5)
    gt, pr, diag = rng.random((3, 4, 3)), rng.random((3, 6, 3)), np.array([1.0, 2.0, 0.5])
    want = np.mean([np.mean([min(np.linalg.norm(g - p) for p in pr[t]) for g in gt[t]]) / diag[t] for t in range(3)])
    rev = np.mean([np.mean([min(np.linalg.norm(g - p) for g in gt[t]) for p in pr[t]]) / diag[t] for t in range(3)])
    r = skeleton_distance(pr, gt, diag)
    assert r["distance"] == pytest.approx(want) and r["distance_pred_to_gt"] == pytest.approx(rev)
    assert (r["gt_joints"], r["pred_joints"]) == (4, 6)


def test_limb_coverage_goes_on_to_the_end_joints_tip():
    # a body 0 -> 1 and a leg 1 -> 2 whose last bone ends 2 below j2 (a hoof below the knee)
    parents = np.array([-1, 0, 1])
    gt = np.repeat(np.array([[[0, 0, 5], [1, 0, 5], [1, -1, 5]]], float), 2, 0)
    tip = np.repeat(np.array([[1, -3, 5]], float), 2, 0)
    diag = np.full(2, 4.0)
    pred = np.repeat(np.array([[[1, -0.5, 5], [1, -2.5, 5]]]), 2, 0)  # a joint on the leg's bone, one on its last
    names = ["body", "hip", "knee"]
    short = limb_coverage(pred, gt, parents, diag, names=names, branch=False)
    assert not short["to_tip"] and not short["limbs"][0]["to_tip"]
    assert not short["limbs"][0]["covered"] and abs(short["limbs"][0]["tol_needed"] - 1.5 / 4) < 1e-12
    full = limb_coverage(pred, gt, parents, diag, names=names, branch=False, tips={2: tip})
    assert full["to_tip"] and full["limbs"][0]["to_tip"] and full["limbs"][0]["covered"]
    assert full["limbs"][0]["tol_needed"] == 0.0
    # the tip lengthens the chain hip -> knee -> tip to 3: its joints sit at 0.5 / 3 and 2.5 / 3 along it
    assert abs(full["limbs"][0]["median_span"] - 2 / 3) < 1e-12
    # a tip for another joint leaves the limb as it was
    other = limb_coverage(pred, gt, parents, diag, names=names, branch=False, tips={1: tip})
    assert not other["to_tip"] and not other["limbs"][0]["to_tip"] and not other["limbs"][0]["covered"]


def test_empty_bones_are_the_largest_weight_of_no_vertex():
    W = np.array([[0.6, 0.3, 0.1, 0.0], [0.2, 0.7, 0.1, 0.0], [0.5, 0.1, 0.4, 0.0]])  # bone 2 weighs, owns nothing
    assert empty_bones(W) == {"count": 4, "empty": [2, 3]}
    assert empty_bones(W[:, :2]) == {"count": 2, "empty": []}
    with pytest.raises(ValueError, match="empty_bones"):
        empty_bones(W[0])


def test_joints_inside_a_moving_box():
    box = trimesh.creation.box(extents=(2.0, 1.0, 1.0))
    V0 = np.asarray(box.vertices)
    shift = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 3.0]])  # two frames, the box moves
    verts = V0[None] + shift[:, None]
    # joint 0 inside in both frames; joint 1 inside at frame 0, 0.25 outside (along y) at frame 1
    joints = np.array([[[0.2, 0.1, 0.0], [0.0, 0.3, 0.0]], [[0.7, 0.1, 3.0], [0.5, 0.75, 3.0]]])
    r = joints_inside(joints, verts, box.faces)
    assert r["fraction"] == pytest.approx(3 / 4)
    assert r["per_joint"] == pytest.approx([1.0, 0.5])
    assert r["max_outside"] == pytest.approx(0.25, abs=1e-5)
    with pytest.raises(ValueError, match="joints_inside"):
        joints_inside(joints[:1], verts, box.faces)


def test_limb_coverage_on_a_hand_made_tree():
    # body 0 -> 1; two legs from 1: 1 -> 2 -> 3 and 1 -> 4 -> 5; a tail 0 -> 6
    parents = np.array([-1, 0, 1, 2, 1, 4, 0])
    limbs = gt_limbs(parents, [f"j{i}" for i in range(7)])
    assert sorted(tuple(l["joints"]) for l in limbs) == [(0, 6), (1, 2, 3), (1, 4, 5)]
    pos = np.array([[0, 0, 5], [1, 0, 5], [1, 1, 5], [1, 2, 5], [2, 1, 5], [2, 2, 5], [-1, 0, 5]], float)[None]
    gt = np.repeat(pos, 3, 0)
    diag = np.full(3, 3.0)
    full = limb_coverage(gt, gt, parents, diag)
    assert full["covered"] == full["total"] == 3
    # joints only along the first leg: the other leg and the tail are not covered
    pred = np.repeat(np.array([[[1, 1.2, 5], [1, 1.8, 5]]]), 3, 0)
    part = limb_coverage(pred, gt, parents, diag)
    got = {l["limb"]: l["covered"] for l in part["limbs"]}
    assert got == {"joint_3": True, "joint_5": False, "joint_6": False} and part["covered"] == 1
    # the span along the chain: the leg j1 -> j2 -> j3 is 2 long, its joints sit at 1.2 and 1.8 of it; a knot
    # of two joints near one point spans almost nothing, one joint nothing
    span = {l["limb"]: l["median_span"] for l in part["limbs"]}
    assert abs(span["joint_3"] - 0.3) < 1e-12 and span["joint_5"] == 0.0
    knot = np.repeat(np.array([[[1, 1.2, 5], [1.05, 1.25, 5]]]), 3, 0)
    k3 = {l["limb"]: l for l in limb_coverage(knot, gt, parents, diag)["limbs"]}["joint_3"]
    assert k3["covered"] and abs(k3["median_span"] - 0.025) < 1e-12
    # min_separation (along the chain, a fraction of its length): a knot counts once, so it is one joint, not a
    # chain; the knot's joints sit at 0.6 and 0.625 of the leg, the first leg's joints at 0.6 and 0.9
    k3 = {l["limb"]: l for l in limb_coverage(knot, gt, parents, diag, min_separation=0.15)["limbs"]}["joint_3"]
    assert not k3["covered"] and k3["tol_needed"] is None and k3["median_pred_joints"] == 1
    p3 = {l["limb"]: l for l in limb_coverage(pred, gt, parents, diag, min_separation=0.15)["limbs"]}["joint_3"]
    assert p3["covered"] and p3["tol_needed"] == 0.0
    assert not {l["limb"]: l for l in limb_coverage(pred, gt, parents, diag, min_separation=0.31)["limbs"]}["joint_3"]["covered"]
    wide = limb_coverage(knot, gt, parents, diag, min_separation=0.02)["limbs"]  # just under the knot's 0.025
    assert {l["limb"]: l for l in wide}["joint_3"]["covered"]
    # two joints side by side at one place along the leg count once too
    side = np.repeat(np.array([[[0.95, 1.2, 5], [1.05, 1.2, 5]]]), 3, 0)
    assert not {l["limb"]: l for l in limb_coverage(side, gt, parents, diag, min_separation=0.15)["limbs"]}["joint_3"]["covered"]
    # tol_needed: covered at every tolerance above it, not at or below it
    need = {l["limb"]: l["tol_needed"] for l in part["limbs"]}
    assert need["joint_3"] == 0.0  # both joints on the polyline
    for tol in (0.05, 0.2, 0.3, 0.4, 0.6):
        got = {l["limb"]: l["covered"] for l in limb_coverage(pred, gt, parents, diag, tol=tol)["limbs"]}
        assert got == {k: tol > v for k, v in need.items()}, (tol, need)
    # with a frame moved away, the needed tolerance is the worse of the best half of the frames
    pred3 = pred.copy()
    pred3[0] += np.array([0, 0, 0.6])  # frame 0: 0.2 of the diagonal off
    pred3[1] += np.array([0, 0, 0.3])  # frame 1: 0.1 off; frame 2 on the polyline
    n3 = {l["limb"]: l["tol_needed"] for l in limb_coverage(pred3, gt, parents, diag)["limbs"]}
    assert abs(n3["joint_3"] - 0.1) < 1e-12
    assert limb_coverage(pred[:, :1], gt, parents, diag)["limbs"][0]["tol_needed"] is None  # one joint, two needed
    # branch=False: the limb's own joints only. A joint at the body end (j1, where the legs branch) covers
    # both legs with the branch in the polyline, neither without it; the tail's own chain is the point j6
    hip = np.repeat(np.array([[[1.0, 0.0, 5]]]), 3, 0)
    with_branch = {l["limb"]: l["covered"] for l in limb_coverage(hip, gt, parents, diag, min_joints=1)["limbs"]}
    own = limb_coverage(hip, gt, parents, diag, min_joints=1, branch=False)["limbs"]
    assert with_branch == {"joint_3": True, "joint_5": True, "joint_6": False}  # the tail branches at j0
    assert {l["limb"]: l["covered"] for l in own} == {"joint_3": False, "joint_5": False, "joint_6": False}
    need = {l["limb"]: l["tol_needed"] for l in own}
    assert abs(need["joint_3"] - 1 / 3) < 1e-12 and abs(need["joint_6"] - 2 / 3) < 1e-12  # to j2 (1 away), to j6 (2)


def test_limb_identity_counts_the_frames_where_two_legs_swap():
    # the tree of the test above: legs end at joints 3 and 5, the tail at joint 6
    parents = np.array([-1, 0, 1, 2, 1, 4, 0])
    pos = np.array([[0, 0, 5], [1, 0, 5], [1, 1, 5], [1, 2, 5], [2, 1, 5], [2, 2, 5], [-1, 0, 5]], float)
    T, n = 10, 5
    gt = np.repeat(pos[None], T, 0)
    rng = np.random.default_rng(0)
    jitter = 0.05 * rng.standard_normal((3, n, 3))
    # bones 0 and 1: the two legs' parts, bone 2: the tail's; in frames 7-9 the legs' parts trade places
    verts = np.empty((T, 3 * n, 3))
    for t in range(T):
        a, b = (3, 5) if t < 7 else (5, 3)
        verts[t] = np.concatenate([pos[a] + jitter[0], pos[b] + jitter[1], pos[6] + jitter[2]])
    W = np.zeros((3 * n, 3))
    W[np.arange(3 * n), np.repeat(np.arange(3), n)] = 0.8
    W += 0.1
    # the predictions live in another frame: the alignment maps them back
    sim = Similarity(2.0, np.eye(3), np.array([0.5, -1.0, 3.0]))
    r = limb_identity((verts - sim.translation) / sim.scale, W, gt, parents, sim)
    got = {o["limb"]: (o["bone"], o["kept"], o["swapped"], o["shared"]) for o in r["limbs"]}
    assert got == {"joint_3": (0, 0.7, pytest.approx(0.3), False), "joint_5": (1, 0.7, pytest.approx(0.3), False),
                   "joint_6": (2, 1.0, 0.0, False)}
    assert r["mean_swapped"] == pytest.approx(0.2)
    # without the alignment the nearest vertices are the wrong ones
    assert limb_identity((verts - sim.translation) / sim.scale, W, gt, parents)["mean_swapped"] != pytest.approx(0.2)
    # one part for both legs: shared, and a frame won by the shared bone is not a swap
    W2 = W.copy()
    W2[n:2 * n] = W[:n]
    r2 = limb_identity(verts, W2, gt, parents)
    got2 = {o["limb"]: (o["bone"], o["swapped"], o["shared"]) for o in r2["limbs"]}
    assert got2 == {"joint_3": (0, 0.0, True), "joint_5": (0, 0.0, True), "joint_6": (2, 0.0, False)}


def test_a_hand_is_part_of_its_arm():
    """A joint whose child chains fan out within FAN_DEG (fingers) ends one limb; wider branchings start several."""
    # 0 body; arm 0 -> 1 -> 2 (wrist) -> fingers 3 -> 4, 5 -> 6, 7 -> 8; leg 0 -> 9 -> 10; head 0 -> 11
    parents = np.array([-1, 0, 1, 2, 3, 2, 5, 2, 7, 0, 9, 0])
    pos = np.zeros((12, 3))
    pos[1], pos[2] = [1, 0, 0], [2, 0, 0]
    for k, (a, b) in enumerate([(3, 4), (5, 6), (7, 8)]):  # fingers 10 degrees apart, the middle one longest
        ang = np.deg2rad(10.0 * (k - 1))
        d = np.array([np.cos(ang), np.sin(ang), 0.0])
        pos[a], pos[b] = pos[2] + 0.3 * d, pos[2] + (0.8 if k == 1 else 0.6) * d
    pos[9], pos[10], pos[11] = [0, -1, 0], [0, -2, 0], [-0.5, 0.5, 0]
    names = [f"j{i}" for i in range(12)]
    assert sorted(tuple(l["joints"]) for l in gt_limbs(parents, names)) == [
        (0, 9, 10), (0, 11), (2, 3, 4), (2, 5, 6), (2, 7, 8)]
    assert sorted(tuple(l["joints"]) for l in gt_limbs(parents, names, pos)) == [(0, 1, 2, 5, 6), (0, 9, 10), (0, 11)]
    spread = pos.copy()  # the same fingers 40 degrees apart are branches, not a hand
    for k, (a, b) in enumerate([(3, 4), (5, 6), (7, 8)]):
        ang = np.deg2rad(40.0 * (k - 1))
        d = np.array([np.cos(ang), np.sin(ang), 0.0])
        spread[a], spread[b] = pos[2] + 0.3 * d, pos[2] + 0.6 * d
    assert len(gt_limbs(parents, names, spread)) == 5
