"""Readers (s3o_warp.evaluation.loaders): bad prediction, keypoints and ground-truth files are one clear error each;
the ground truth's non-deforming joints and end joints' tips; BADJA files converted to keypoints.json and read back."""

from __future__ import annotations

import json

import numpy as np
import pytest
from eval_scene import tiny_motion
from scipy.ndimage import distance_transform_edt

from s3o_warp.data.keypoints import (
    BADJA_ANNOTATED,
    BADJA_JOINT_NAMES,
    badja_to_keypoints,
)
from s3o_warp.data.keypoints import main as badja_main
from s3o_warp.data.masks import read_mask
from s3o_warp.errors import InputError
from s3o_warp.evaluation.loaders import (
    load_ground_truth,
    load_keypoints,
    load_predictions,
)


def test_bad_prediction_files(tmp_path):
    with pytest.raises(InputError, match="motion.npz.*not found"):
        load_predictions(tmp_path)
    with pytest.raises(InputError, match="no such USD file"):
        load_predictions(tmp_path / "run.usda")
    with pytest.raises(InputError, match="missing key 'frame_names'"):
        load_predictions(tiny_motion(tmp_path / "a.npz", frame_names=None))
    with pytest.raises(InputError, match=r"'verts_cam' must have shape \(T, N, 3\)"):
        load_predictions(tiny_motion(tmp_path / "b.npz", verts_cam=np.ones((2, 3), np.float32)))
    with pytest.raises(InputError, match="'faces' index vertices outside"):
        load_predictions(tiny_motion(tmp_path / "c.npz", faces=np.array([[0, 1, 5]])))
    with pytest.raises(InputError, match="3 entries but 'verts_cam' has 2"):
        load_predictions(tiny_motion(tmp_path / "d.npz", frame_names=np.array(["a", "b", "c"])))
    with pytest.raises(InputError, match="object arrays"):
        load_predictions(tiny_motion(tmp_path / "e.npz", frame_names=np.array(["a", "b"], dtype=object)))
    with pytest.raises(InputError, match="'K' must have shape"):
        load_predictions(tiny_motion(tmp_path / "f.npz", K=np.eye(4)))
    (tmp_path / "g.npz").write_text("not a zip")
    with pytest.raises(InputError, match="not a readable .npz"):
        load_predictions(tmp_path / "g.npz")
    p = load_predictions(tiny_motion(tmp_path / "ok.npz"))
    assert p.K.shape == (2, 3, 3) and p.frame_names == ["a", "b"] and p.joints_cam is None


def test_bad_keypoints_and_ground_truth_files(tmp_path):
    (tmp_path / "kp.json").write_text("{broken")
    with pytest.raises(InputError, match="kp.json: not valid JSON"):
        load_keypoints(tmp_path / "kp.json")
    (tmp_path / "kp.json").write_text(json.dumps({"names": ["x"], "frames": {"a": [[1, 2, 1]], "b": [[1, 2, 1], [3, 4, 0]]}}))
    with pytest.raises(InputError, match="different keypoint counts"):
        load_keypoints(tmp_path / "kp.json")
    np.savez(tmp_path / "gt2.npz", faces=np.array([[0, 1, 2]]))
    with pytest.raises(InputError, match="missing key 'verts'"):
        load_ground_truth(tmp_path / "gt2.npz")


def test_ground_truth_drops_non_deforming_joints(tmp_path):
    np.savez(tmp_path / "gt.npz", verts=np.ones((2, 3, 3)), faces=np.array([[0, 1, 2]]), joints=np.arange(18.0).reshape(2, 3, 3),
             joint_names=np.array(["a", "ik", "b"]), joint_deforming=np.array([True, False, True]))
    gt = load_ground_truth(tmp_path)
    assert gt.joints.shape == (2, 2, 3) and gt.joint_names == ["a", "b"]
    np.testing.assert_array_equal(gt.joints[:, 1], np.arange(18.0).reshape(2, 3, 3)[:, 2])


def test_ground_truth_reads_end_joints_tips(tmp_path):
    verts = np.arange(2 * 4 * 3, dtype=np.float32).reshape(2, 4, 3)
    np.savez(tmp_path / "gt.npz", verts=verts, faces=np.array([[0, 1, 2]]), joints=np.zeros((2, 3, 3)),
             joint_names=np.array(["a", "ik", "b"]), joint_deforming=np.array([True, False, True]),
             keypoint_names=np.array(["b_tip", "ik_tip", "a", "zz_tip"]), keypoint_vertex=np.array([3, 1, 0, 2]))
    gt = load_ground_truth(tmp_path)
    assert list(gt.tips) == ["b"]  # a kept joint's tip; not a dropped joint's, a plain keypoint or an unknown name
    np.testing.assert_array_equal(gt.tips["b"], verts[:, 3])
    np.savez(tmp_path / "gt.npz", verts=verts, faces=np.array([[0, 1, 2]]), joints=np.zeros((2, 1, 3)),
             joint_names=np.array(["b"]), keypoint_names=np.array(["b_tip"]), keypoint_vertex=np.array([4]))
    with pytest.raises(InputError, match="'b_tip' names vertex 4, but there are 4"):
        load_ground_truth(tmp_path)


# --------------------------------------------------------------------------------------------------
# BADJA
# --------------------------------------------------------------------------------------------------


def test_badja_conversion_hand_made(tmp_path):
    joints = [[0, 0]] * 37
    vis = [False] * 37
    joints[8], vis[8] = [539.5, 959.5], True  # the image centre of 1080 x 1920
    joints[33], vis[33] = [1079.5, -0.5], True  # bottom-left corner of the image
    data = [{"image_path": "DAVIS/JPEGImages/Full-Resolution/cows/00005.jpg", "segmentation_path": "", "joints": joints,
             "visibility": vis}]
    kp = badja_to_keypoints(data, (480, 854))
    assert kp["names"] == [BADJA_JOINT_NAMES[s] for s in BADJA_ANNOTATED] and len(kp["names"]) == 20
    rows = np.array(kp["frames"]["00005"])
    np.testing.assert_allclose(rows[0], [426.5, 239.5, 1])  # centre maps to centre
    np.testing.assert_allclose(rows[BADJA_ANNOTATED.index(33)], [-0.5, 479.5, 1])  # corner maps to corner
    assert rows[:, 2].sum() == 2
    assert len(badja_to_keypoints(data, (480, 854), annotated_only=False)["names"]) == 37
    with pytest.raises(InputError, match="expected \\(37, 2\\)"):
        badja_to_keypoints([dict(data[0], joints=joints[:5])], (480, 854))
    with pytest.raises(InputError, match="lacks image_path"):
        badja_to_keypoints([{"joints": joints}], (480, 854))
    (tmp_path / "b.json").write_text(json.dumps({"not": "a list"}))
    with pytest.raises(InputError, match="expected a JSON list"):
        badja_to_keypoints(tmp_path / "b.json", (480, 854))


@pytest.mark.parametrize("animal", ["cows", "dog"])
def test_badja_keypoints_fall_inside_davis_masks(shared_data, animal, tmp_path):
    src = shared_data / "badja" / f"{animal}.json"
    masks = shared_data / "davis" / "Annotations" / "480p" / animal
    if not src.exists() or not masks.is_dir():
        pytest.skip(f"{src} or {masks} not in the shared data")
    out = tmp_path / "keypoints.json"
    assert badja_main([str(src), str(out), "--frames", str(shared_data / "davis" / "JPEGImages" / "480p" / animal)]) == 0
    kp = load_keypoints(out)
    dist = []
    for stem, rows in kp.frames.items():
        m = read_mask(masks / f"{stem}.png")
        assert m.shape == (480, 854)
        dt = distance_transform_edt(~m)
        for x, y, v in rows:
            if v:
                dist.append(dt[int(np.clip(round(y), 0, 479)), int(np.clip(round(x), 0, 853))])
    dist = np.array(dist)
    assert len(dist) > 150
    # measured: cows 96.9% inside, 99.7% within 3 px, all within 5 px; dog 99.5% inside, all within 3 px
    assert (dist == 0).mean() > 0.95
    assert (dist <= 5).mean() > 0.99
