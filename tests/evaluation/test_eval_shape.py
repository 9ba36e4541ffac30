"""3D shape scores (s3o_warp.evaluation.shape): Umeyama, surface sampling, Chamfer / F-score against dense distances,
and the sequence's and each frame's similarity alignment recovering known transforms."""

from __future__ import annotations

import math

import numpy as np
import pytest
from eval_scene import rot, two_box_sequence

from s3o_warp.evaluation.shape import (
    bbox_diagonal,
    chamfer_fscore,
    frame_similarities,
    sample_surface,
    shape_metrics,
    umeyama,
)
from s3o_warp.evaluation.skeleton import skeleton_distance


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(50, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    dst = 2.5 * src @ R.T + [0.3, -1.0, 4.0]
    s, R2, t = umeyama(src, dst)
    assert s == pytest.approx(2.5, rel=1e-10)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose(t, [0.3, -1.0, 4.0], atol=1e-10)
    # a reflection is never returned
    s, R3, _ = umeyama(src, src * [1, 1, -1])
    assert np.linalg.det(R3) == pytest.approx(1.0)


def test_sample_surface_is_on_the_mesh_and_area_weighted():
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [3, 0, 1], [0, 2, 1]], float)  # areas 0.5 and 3
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    p = sample_surface(verts, faces, 20000, seed=3)
    on_first = p[:, 2] == 0
    assert np.all(on_first | (np.abs(p[:, 2] - 1) < 1e-12))
    assert on_first.mean() == pytest.approx(0.5 / 3.5, abs=0.01)
    q = p[on_first]
    assert np.all(q[:, :2] >= -1e-12) and np.all(q[:, 0] + q[:, 1] <= 1 + 1e-12)
    np.testing.assert_array_equal(p, sample_surface(verts, faces, 20000, seed=3))  # fixed seed


def test_chamfer_fscore_against_dense_distances():
    rng = np.random.default_rng(2)
    a, b = rng.random((300, 3)), rng.random((200, 3)) + 0.05
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)
    r = chamfer_fscore(a, b, threshold=0.08)
    assert r["chamfer"] == pytest.approx(0.5 * (d.min(1).mean() + d.min(0).mean()), rel=1e-12)
    prec, rec = (d.min(1) < 0.08).mean(), (d.min(0) < 0.08).mean()
    assert r["precision"] == pytest.approx(prec) and r["recall"] == pytest.approx(rec)
    assert r["fscore"] == pytest.approx(2 * prec * rec / (prec + rec))
    assert chamfer_fscore(a, a, 1e-3) == {"chamfer": 0.0, "precision": 1.0, "recall": 1.0, "fscore": 1.0}


def test_alignment_recovers_a_known_similarity():
    verts, faces, joints, _ = two_box_sequence()
    s, R, t = 0.5, rot("y", 0.12) @ rot("z", -0.08), np.array([0.05, -0.03, 0.1])
    pred = ((verts.astype(np.float64) - t) @ R) / s  # so that s R pred + t = gt
    out, sim = shape_metrics(pred, faces, verts, faces, n_points=2000, icp_points=6000)
    assert sim.scale == pytest.approx(s, rel=1e-4)
    np.testing.assert_allclose(sim.rotation, R, atol=1e-4)
    np.testing.assert_allclose(sim.translation, t, atol=1e-3)
    assert out["chamfer"] < 1e-4 and out["fscore"] == 1.0
    pj = ((joints.astype(np.float64) - t) @ R) / s
    sk = skeleton_distance(pj, joints, bbox_diagonal(verts), sim)
    assert sk["distance"] < 1e-4 and (sk["gt_joints"], sk["pred_joints"]) == (3, 3)
    # without the alignment the same prediction is far off: the metric can fail
    far = skeleton_distance(pj, joints, bbox_diagonal(verts))
    assert far["distance"] > 0.5


def test_frame_similarities_take_out_each_frames_own_pose_error():
    """A prediction whose every frame is off by its own similarity: the sequence alignment cannot undo it, the
    per-frame alignments (the sequence's, then ICP on the frame alone) map its joints onto the ground truth."""
    verts, faces, joints, _ = two_box_sequence()
    T = len(verts)
    pred, pj = np.empty(verts.shape), np.empty(joints.shape)
    for t in range(T):  # x = (g - tr) @ R / s, so that s R x + tr = g; each frame its own
        s, R = 1.0 + 0.04 * (-1) ** t, rot("y", 0.1 * math.sin(2.0 * t)) @ rot("z", 0.05 * t)
        tr = np.array([0.2 * math.sin(t), 0.05 * t, 0.3 * math.cos(1.7 * t)])
        pred[t], pj[t] = ((verts[t] - tr) @ R) / s, ((joints[t] - tr) @ R) / s
    _, sim = shape_metrics(pred, faces, verts, faces, n_points=1000, icp_points=6000)
    diag = bbox_diagonal(verts)
    seq_err = np.linalg.norm(sim(pj) - joints, axis=-1).max(1) / diag
    sims = frame_similarities(pred, faces, verts, faces, sim, n_points=4000)
    err = np.stack([np.linalg.norm(f(pj[t]) - joints[t], axis=-1).max() for t, f in enumerate(sims)]) / diag
    assert seq_err.max() > 0.1 and err.max() < 0.01, (seq_err, err)
    # one similarity for every frame (no error of its own): each frame's ICP stays at the sequence's
    _, same = shape_metrics(pred[:1].repeat(3, 0), faces, verts[:1].repeat(3, 0), faces, n_points=1000)
    for f in frame_similarities(pred[:1].repeat(3, 0), faces, verts[:1].repeat(3, 0), faces, same):
        assert np.linalg.norm(f(pj[0]) - joints[0], axis=-1).max() / diag[0] < 0.01
