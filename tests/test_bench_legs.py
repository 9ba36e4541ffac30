"""scripts/bench_legs.py: the depth of the surface under each side's keypoints, and the phases."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import bench_legs  # noqa: E402


def test_keypoint_depths_by_group():
    # four keypoints: a near end on its own limb, a far end whose surface is at the near limb's depth, a far end
    # half way, and a near rest keypoint on its own limb
    own = np.array([[0, 0, 5.0], [0, 0, 6.0], [1, 0, 6.0], [0, 1, 5.0]])
    other = np.array([[0, 0, 6.0], [0, 0, 5.0], [1, 0, 5.0], [0, 1, 6.0]])
    pts = np.array([[0, 0, 5.05], [0, 0, 5.0], [1, 0, 5.5], [0, 1, 5.0]])
    near = own[:, 2] < other[:, 2]
    end = np.array([True, True, True, False])
    d = bench_legs.keypoint_depths(pts, own, other, near, end)
    assert d["ends_near"]["n"] == 1 and d["ends_near"]["other_leg"] == 0.0
    assert d["ends_near"]["depth_share"] == pytest.approx(0.05)
    assert d["ends_far"]["n"] == 2
    assert d["ends_far"]["other_leg"] == pytest.approx(0.5)  # the one at the near limb's depth; half way is a tie
    assert d["ends_far"]["depth_share"] == pytest.approx(0.75)  # median of 1 and 0.5
    assert d["rest_near"] == {"n": 1, "other_leg": 0.0, "depth_share": 0.0}
    assert d["rest_far"] == {"n": 0, "other_leg": None, "depth_share": None}


def test_phase_names():
    f = bench_legs.phase_name
    assert f(Path("step-1-warmup-000000.pt"), 200) == "coarse"
    assert f(Path("step-2-joint-000000.pt"), 200) == "warmup"
    assert f(Path("step-2-joint-000200.pt"), 200) == "epoch 0"
    assert f(Path("step-2-joint-001000.pt"), 200) == "epoch 4"
    assert f(Path("step-3-done-000000.pt"), 200) == "done"
