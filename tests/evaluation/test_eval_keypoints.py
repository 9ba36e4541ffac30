"""Keypoint roles from names, the side facing the camera, and PCK-T by role (s3o_warp.evaluation.keypoints) against
hand-counted cases and a loop over the frames and keypoints."""

from __future__ import annotations

import numpy as np

from s3o_warp.data.keypoints import BADJA_ANNOTATED, BADJA_JOINT_NAMES
from s3o_warp.evaluation.keypoints import counterparts, facing_sides, keypoint_role, name_tokens, pck_groups


def test_roles_of_the_models_and_badja_names():
    assert name_tokens("b_LeftHand_011_tip") == ["b", "left", "hand", "011", "tip"]
    assert name_tokens("FFB.L_tip") == ["ffb", "l", "tip"]
    ends = {"b_RightHand_08_tip": "right", "b_LeftFoot02_018_tip": "left", "FF.L_tip": "left", "FFB.R_tip": "right",
            "FrontLowerLeg.L_tip": "left", "BackLowerLeg.R_tip": "right", "Foot.L_tip": "left",
            "Middle2.R_tip": "right", "foot_fl": "left", "foot_br": "right", "lower_left_3": "left",
            "upper_right_2": "right"}
    rest = {"b_RightForeArm_07": "right", "b_LeftLeg02_016": "left", "FrontLowerLeg.L": "left", "Ear4.R_tip": "right",
            "LowerArm.L": "left", "knee_fr": "right", "hip_bl": "left", "ear_tip_l": "left", "upper_left_1": "left",
            "right_ear": "right", "Head": None, "Tail7_tip": None, "nose": None, "withers": None, "b_Neck_04": None}
    for name, side in ends.items():
        assert keypoint_role(name).end and keypoint_role(name).side == side, name
    for name, side in rest.items():
        assert not keypoint_role(name).end and keypoint_role(name).side == side, name
    badja = [BADJA_JOINT_NAMES[i] for i in BADJA_ANNOTATED]
    assert sum(keypoint_role(n).end for n in badja) == 8  # joints 2 and 3 of the four legs


def test_facing_from_depth_and_from_the_image():
    names = ["nose", "tail_0", "foot_fl", "foot_fr"]
    depth = np.array([[5, 5, 4.0, 6.0], [5, 5, 6.0, 4.0], [5, 5, 5, 5]])
    kp = np.zeros((3, 4, 3))
    assert facing_sides(names, kp, depth) == ["left", "right", None]
    # from the image: the head right of the tail shows the right side; end on (head above the tail) says nothing
    kp = np.array([[[90, 10, 1], [10, 10, 1], [80, 50, 1], [20, 50, 1]],
                   [[10, 10, 1], [90, 10, 1], [80, 50, 1], [20, 50, 1]],
                   [[50, 10, 1], [51, 60, 1], [40, 50, 1], [60, 50, 1]],
                   [[90, 10, 0], [10, 10, 1], [80, 50, 1], [20, 50, 1]]], float)  # the nose hidden
    assert facing_sides(names, kp) == ["right", "left", None, None]
    assert facing_sides(["nose", "tail"], kp[:, :2]) == [None] * 4  # nothing named for a side
    # the Quaternius models name no nose: their ears and neck are the front end
    assert facing_sides(["Ear4.L_tip", "Tail1", "FF.L_tip", "FF.R_tip"], kp[:2]) == ["right", "left"]


def test_groups_add_up_the_frames_and_keypoints_that_belong():
    rng = np.random.default_rng(0)
    names = ["nose", "foot_fl", "foot_fr", "knee_fl", "knee_fr", "tail_tip"]
    A, P = 5, len(names)
    total = rng.integers(0, 9, (A, P))
    correct = rng.integers(0, 9, (A, P)) % (total + 1)
    facing = ["left", "right", None, "right", "left"]
    g = pck_groups(names, correct, total, facing)
    side = {"foot_fl": "left", "foot_fr": "right", "knee_fl": "left", "knee_fr": "right"}
    want = {k: [0, 0] for k in ("ends", "rest", "near", "far", "ends_near", "ends_far")}
    for a in range(A):
        for p, n in enumerate(names):
            c, t = correct[a, p], total[a, p]
            end = n.startswith("foot")
            for k in ("ends",) if end else ("rest",):
                want[k][0] += c
                want[k][1] += t
            if n in side and facing[a] is not None:
                k = "near" if side[n] == facing[a] else "far"
                for kk in (k, "ends_" + k) if end else (k,):
                    want[kk][0] += c
                    want[kk][1] += t
    for k, (c, t) in want.items():
        assert (g[k]["correct"], g[k]["total"]) == (c, t), k
        assert g[k]["pck"] == (100.0 * c / t if t else None)
    assert g["ends"]["keypoints"] == ["foot_fl", "foot_fr"] and g["frames_with_side"] == 4
    rate = correct.sum(0) / np.maximum(total.sum(0), 1)
    assert g["worst"]["keypoint"] == names[int(np.argmin(np.where(total.sum(0) > 0, rate, np.inf)))]


def test_counterparts_mirror_the_side_word():
    names = ["FF.L_tip", "FF.R_tip", "upper_left_1", "upper_right_1", "upper_left_2", "upper_right_2",
             "b_LeftFoot02_018_tip", "b_RightFoot02_022_tip", "foot_fl", "foot_fr", "foot_bl", "nose", "Tail7_tip"]
    c = counterparts(names)
    by = {n: (names[j] if j is not None else None) for n, j in zip(names, c)}
    assert by["FF.L_tip"] == "FF.R_tip" and by["FF.R_tip"] == "FF.L_tip"
    assert by["upper_left_1"] == "upper_right_1" and by["upper_right_2"] == "upper_left_2"
    assert by["b_LeftFoot02_018_tip"] == "b_RightFoot02_022_tip"  # the bone numbers differ
    assert by["foot_fl"] == "foot_fr" and by["foot_bl"] is None  # front left to front right, not back right
    assert by["nose"] is None and by["Tail7_tip"] is None
