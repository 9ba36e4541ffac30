"""The procedural lizard: a closed skin, a spine with four short legs and a tail, a crawl that undulates."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from s3o_warp.errors import InputError
from s3o_warp.evaluation.skeleton import gt_limbs
from s3o_warp.synth import make_sequence
from s3o_warp.synth.lizard import build_lizard, lizard_keypoints


@pytest.fixture(scope="module")
def lizard():
    return build_lizard(frames=30, fps=30.0, seed=0)


def test_lizard_body_plan(lizard):
    names, parents = lizard.joint_names, lizard.parents
    assert trimesh.Trimesh(lizard.rest_verts, lizard.faces, process=False).is_watertight
    assert len(names) == 24 and int((parents >= 0).sum()) == 23  # 23 bones, one root (the pelvis)
    assert all(parents[j] < j for j in range(len(names)) if parents[j] >= 0)
    limbs = {lb["name"]: [names[j] for j in lb["joints"]] for lb in gt_limbs(parents, names)}
    assert sorted(limbs) == ["foot_bl", "foot_br", "foot_fl", "foot_fr", "snout", "tail_tip"]
    assert limbs["foot_fl"] == ["chest", "shoulder_fl", "elbow_fl", "foot_fl"]
    assert limbs["foot_br"] == ["pelvis", "hip_br", "knee_br", "foot_br"]
    assert limbs["tail_tip"] == ["pelvis", "tail_1", "tail_2", "tail_3", "tail_4", "tail_tip"]
    rest = lizard.rest_joints
    length = np.ptp(lizard.rest_verts[:, 0])
    leg = np.linalg.norm(rest[names.index("foot_fl")] - rest[names.index("shoulder_fl")])
    assert length > 1.4 and leg < 0.15 * length  # a long body on short legs
    assert np.ptp(lizard.rest_verts[:, 1]) < 0.15 * length and abs(lizard.rest_verts[:, 1].min()) < 0.02  # low, on the ground
    assert rest[names.index("foot_fl"), 2] < 0 < rest[names.index("foot_fr"), 2]  # left legs on -z
    np.testing.assert_allclose(lizard.weights.sum(1), 1.0, atol=1e-5)
    kp, idx = lizard_keypoints(lizard)
    assert len(kp) == len(set(idx.tolist())) == 22


def test_lizard_crawl_undulates(lizard):
    names = lizard.joint_names
    j = {n: lizard.joints[:, names.index(n)] for n in names}
    # the body bends sideways, more toward the tail, and the bend travels backward along it
    side = {n: j[n][:, 2] - j["pelvis"][:, 2] for n in ("tail_2", "tail_tip", "snout")}
    assert np.ptp(side["tail_tip"]) > max(0.25, 1.5 * np.ptp(side["snout"])) and np.ptp(side["snout"]) > 0.02
    lag = [np.corrcoef(side["tail_2"][:-k or None], side["tail_tip"][k:])[0, 1] for k in range(8)]
    assert int(np.argmax(lag)) > 0  # the tail tip follows the tail's middle
    # diagonal pairs step together, the two pairs in antiphase
    rel = {leg: j[f"foot_{leg}"][:, 0] - j["chest" if leg[0] == "f" else "pelvis"][:, 0] for leg in ("fl", "fr", "bl", "br")}
    assert np.ptp(rel["fl"]) > 0.05
    corr = lambda a, b: np.corrcoef(rel[a], rel[b])[0, 1]  # noqa: E731
    assert corr("fl", "br") > 0.6 and corr("fr", "bl") > 0.6 and corr("fl", "fr") < -0.6 and corr("bl", "br") < -0.6
    assert j["pelvis"][-1, 0] > j["pelvis"][0, 0] + 0.05  # crawls forward
    again = build_lizard(frames=30, fps=30.0, seed=0)
    np.testing.assert_array_equal(again.verts, lizard.verts)


def test_lizard_sequence(tmp_path):
    out = make_sequence(tmp_path / "liz", source="lizard", frames=3, size=(80, 60), progress=False)
    gt = np.load(out / "ground_truth" / "ground_truth.npz")
    assert gt["joints"].shape == (3, 24, 3) and str(gt["clip"]) == "crawl"
    assert len(json.loads((out / "keypoints.json").read_text())["names"]) == 22
    with pytest.raises(InputError, match="only the clip 'crawl'"):
        make_sequence(tmp_path / "liz2", source="lizard", clip="walk", frames=2, progress=False)
    with pytest.raises(InputError, match="frames"):
        build_lizard(frames=0)
