"""Image-space scores (s3o_warp.evaluation.image): mask IoU, the surface point under a keypoint and PCK-T transfer,
checked against hand-made cases and the loop twin of PCK-T; the numpy projection they use against the torch one."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from eval_scene import naive_pckt

from s3o_warp.evaluation.image import GAP_BANDS, mask_iou, pck_transfer, surface_under_keypoints
from s3o_warp.geometry import project, project_np


def _fast_pckt(kp, face_index, bary, verts, faces, K, area, **kw):
    A, P = kp.shape[:2]
    kf = np.zeros((A, P), np.int64)
    kb = np.zeros((A, P, 3))
    for a in range(A):
        kf[a], kb[a], _ = surface_under_keypoints(face_index[a], bary[a], kp[a, :, :2])
    return pck_transfer(kp, verts, faces, K, kf, kb, area, **kw)


def test_mask_iou_hand_made():
    a = np.zeros((3, 4, 4), bool)
    b = np.zeros((3, 4, 4), bool)
    a[0, :2] = True  # 8 px
    b[0, 1:3] = True  # 8 px, 4 shared
    a[1, 0, 0] = True  # disjoint
    b[1, 3, 3] = True
    np.testing.assert_allclose(mask_iou(a, b), [4 / 12, 0.0, 1.0])  # frame 2: both empty
    with pytest.raises(ValueError, match="shapes differ"):
        mask_iou(a, b[:2])


def test_pck_transfer_matches_naive_loops():
    rng = np.random.default_rng(4)
    A, P, h, w, nv = 4, 6, 7, 9, 10
    faces = rng.integers(0, nv, size=(5, 3))
    face_index = np.where(rng.random((A, h, w)) < 0.4, rng.integers(0, 5, size=(A, h, w)), -1)
    face_index[2] = -1  # an empty render: its keypoints keep their position
    bary = rng.dirichlet([1, 1, 1], size=(A, h, w))
    verts = np.concatenate([rng.uniform(-1, 1, (A, nv, 2)), rng.uniform(3, 5, (A, nv, 1))], -1)
    K = np.stack([np.array([[30 + a, 0, 4], [0, 28, 3.5], [0, 0, 1]]) for a in range(A)])
    kp = np.concatenate([rng.uniform(-2, w + 1, (A, P, 1)), rng.uniform(-2, h + 1, (A, P, 1)),
                         (rng.random((A, P, 1)) < 0.8)], -1)
    area = rng.integers(10, 40, size=A)
    for mode in ("reference", "target"):
        c0, t0, pred0 = naive_pckt(kp, face_index, bary, verts, faces, K, area, 0.3, mode)
        r = _fast_pckt(kp, face_index, bary, verts, faces, K, area, alpha=0.3, threshold_frame=mode)
        off = ~np.eye(A, dtype=bool)
        np.testing.assert_allclose(r["pred"][off], pred0[off], rtol=0, atol=1e-9)
        assert (r["correct"], r["total"]) == (c0, t0)
        assert 0 < c0 < t0  # both outcomes occur, so the test can fail
        assert r["pairs"] == A * (A - 1)
        assert r["per_keypoint_total"].sum() == t0 and r["per_keypoint_correct"].sum() == c0
        # by frame gap: the same pairs counted by band, from the loops' transferred positions
        fidx = np.array([0, 2, 7, 30])
        rg = _fast_pckt(kp, face_index, bary, verts, faces, K, area, alpha=0.3, threshold_frame=mode,
                        frame_index=fidx)
        want_c, want_t = np.zeros(4, int), np.zeros(4, int)
        frame_c, frame_t = np.zeros((A, P), int), np.zeros((A, P), int)  # per reference frame and keypoint
        for i in range(A):
            for j in range(A):
                for p in range(P):
                    if i == j or kp[i, p, 2] < 0.5 or kp[j, p, 2] < 0.5:
                        continue
                    b = int(np.digitize(abs(fidx[i] - fidx[j]), GAP_BANDS)) - 1
                    thr = 0.3 * np.sqrt(area[i if mode == "reference" else j])
                    ok = np.linalg.norm(pred0[i, j, p] - kp[j, p, :2]) < thr
                    want_t[b] += 1
                    want_c[b] += ok
                    frame_t[i, p] += 1
                    frame_c[i, p] += ok
        np.testing.assert_array_equal(r["per_frame_keypoint_total"], frame_t)
        np.testing.assert_array_equal(r["per_frame_keypoint_correct"], frame_c)
        assert 0 < frame_c.sum() < frame_t.sum()
        assert [g["frames"] for g in rg["by_gap"]] == ["1-3", "4-11", "12-23", "24+"]
        assert [g["total"] for g in rg["by_gap"]] == want_t.tolist() and want_t.all()
        assert [g["correct"] for g in rg["by_gap"]] == want_c.tolist()
        assert [g["total"] for g in r["by_gap"]] == [t0, 0, 0, 0]  # default: frames 0..A-1, all within 3
        # one reference frame per chunk (long videos) and no pair arrays: the same counts
        rc = _fast_pckt(kp, face_index, bary, verts, faces, K, area, alpha=0.3, threshold_frame=mode,
                        chunk_elements=1, pair_limit=0)
        assert (rc["correct"], rc["total"]) == (c0, t0) and rc["pred"] is None
        np.testing.assert_array_equal(rc["per_keypoint_correct"], r["per_keypoint_correct"])
        np.testing.assert_array_equal(rc["per_frame_keypoint_correct"], r["per_frame_keypoint_correct"])
    with pytest.raises(ValueError, match="threshold_frame"):
        _fast_pckt(kp, face_index, bary, verts, faces, K, area, threshold_frame="middle")


def test_pck_transfer_translating_plane_is_exact():
    """A fronto-parallel triangle at depth z moving by dx: every keypoint moves by f * dx / z pixels."""
    f, z, h, w = 50.0, 2.0, 6, 8
    tri = np.array([[-5, -5, z], [5, -5, z], [0, 5, z]])
    verts = np.stack([tri, tri + [0.1, 0, 0], tri + [0.1, -0.04, 0]])
    K = np.broadcast_to(np.array([[f, 0, 3.5], [0, f, 2.5], [0, 0, 1]]), (3, 3, 3))
    fi = np.full((3, h, w), -1)
    fi[:, 1:5, 2:6] = 0
    bary = np.random.default_rng(0).dirichlet([1, 1, 1], size=(3, h, w))
    kp = np.array([[[3.2, 2.1, 1], [0.0, 0.0, 1]], [[5.7, 2.1, 1], [2.5, 0.0, 1]], [[5.7, 1.1, 0], [2.5, -1.0, 1]]])
    r = _fast_pckt(kp, fi, bary, verts, np.array([[0, 1, 2]]), K, np.array([100, 100, 100]))
    np.testing.assert_allclose(r["pred"][0, 1], kp[0, :, :2] + [2.5, 0.0], atol=1e-9)  # off-silhouette keypoint too
    np.testing.assert_allclose(r["pred"][0, 2], kp[0, :, :2] + [2.5, -1.0], atol=1e-9)
    np.testing.assert_allclose(r["pred"][2, 0], kp[2, :, :2] - [2.5, -1.0], atol=1e-9)
    # scored pairs: keypoint 0 is invisible in frame 2; keypoint 1 everywhere: 2 + 6
    assert r["total"] == 8 and r["correct"] == 8


def test_surface_under_keypoints_prefers_the_pixel_itself():
    fi = np.full((5, 5), -1)
    fi[2, 2], fi[2, 3], fi[0, 0] = 7, 8, 9
    bary = np.zeros((5, 5, 3))
    bary[2, 2] = [0.2, 0.3, 0.5]
    face, w, px = surface_under_keypoints(fi, bary, np.array([[2.4, 1.6], [3.6, 2.0], [0.2, 0.4], [-9.0, -9.0]]))
    np.testing.assert_array_equal(face, [7, 8, 9, 9])
    np.testing.assert_array_equal(px, [[2, 2], [3, 2], [0, 0], [0, 0]])
    np.testing.assert_allclose(w[0], [0.2, 0.3, 0.5])
    face, _, _ = surface_under_keypoints(np.full((3, 3), -1), np.zeros((3, 3, 3)), np.zeros((2, 2)))
    np.testing.assert_array_equal(face, [-1, -1])


def test_numpy_projection_matches_the_torch_one():
    """geometry.project_np (numpy: evaluation, export, synthetic data) and geometry.project (torch: the fit) agree,
    per frame's K and with one K for every frame."""
    rng = np.random.default_rng(6)
    X = np.concatenate([rng.uniform(-1, 1, (3, 7, 2)), rng.uniform(2, 5, (3, 7, 1))], -1)
    K = np.stack([np.array([[80.0 + t, 0.5 * t, 31.5], [0, 78.0 - t, 23.5], [0, 0, 1]]) for t in range(3)])
    want = project(torch.from_numpy(X), torch.from_numpy(K)).numpy()
    np.testing.assert_allclose(project_np(X, K[:, None]), want, rtol=0, atol=1e-12)
    np.testing.assert_allclose(project_np(X, K[0]), project(torch.from_numpy(X), torch.from_numpy(K[0])).numpy(),
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(project_np(X[0, 0], K[0]), want[0, 0], rtol=0, atol=1e-12)  # one point
