"""Evaluation metrics: IoU, PCK-T, 3D alignment / Chamfer / F-score, skeleton distance, BADJA, CLI.

Pure parts are checked against direct naive implementations (loops, dense distance matrices); the
whole-run path scores a small moving two-box sequence, built and rendered here, against itself (the
perfect scores) and against a prediction frozen at its first frame (clearly worse).
"""

from __future__ import annotations

import json
import math
import re
import runpy
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from s3o_warp.evaluation import metrics as M
from s3o_warp.data.keypoints import BADJA_ANNOTATED, BADJA_JOINT_NAMES, badja_to_keypoints, write_keypoints
from s3o_warp.errors import InputError
from s3o_warp.data.masks import read_mask

REPO = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------------------------------
# naive twins
# --------------------------------------------------------------------------------------------------


def _proj(K, X):
    p = K @ X
    return p[:2] / p[2]


def naive_pckt(kp, face_index, bary, verts, faces, K, area, alpha=0.2, threshold_frame="reference"):
    """Loops over pairs, keypoints and pixels, as LASR's eval_badja.py does it (one pair at a time)."""
    A, P = kp.shape[:2]
    pred = np.zeros((A, A, P, 2))
    correct = total = 0
    for i in range(A):
        fg = [(r, c) for r in range(face_index.shape[1]) for c in range(face_index.shape[2]) if face_index[i, r, c] >= 0]
        for j in range(A):
            if i == j:
                continue
            for p in range(P):
                x, y = kp[i, p, :2]
                if fg:
                    r, c = min(fg, key=lambda rc: (rc[1] - x) ** 2 + (rc[0] - y) ** 2)
                    f, b = face_index[i, r, c], bary[i, r, c].astype(np.float64)
                    Xi = sum(b[k] * verts[i, faces[f, k]].astype(np.float64) for k in range(3))
                    Xj = sum(b[k] * verts[j, faces[f, k]].astype(np.float64) for k in range(3))
                    pred[i, j, p] = kp[i, p, :2] + _proj(K[j], Xj) - _proj(K[i], Xi)
                else:
                    pred[i, j, p] = kp[i, p, :2]
                if kp[i, p, 2] > 0.5 and kp[j, p, 2] > 0.5:
                    total += 1
                    thr = alpha * math.sqrt(area[i] if threshold_frame == "reference" else area[j])
                    correct += np.linalg.norm(pred[i, j, p] - kp[j, p, :2]) < thr
    return correct, total, pred


def _fast_pckt(kp, face_index, bary, verts, faces, K, area, **kw):
    A, P = kp.shape[:2]
    kf = np.zeros((A, P), np.int64)
    kb = np.zeros((A, P, 3))
    for a in range(A):
        kf[a], kb[a], _ = M.surface_under_keypoints(face_index[a], bary[a], kp[a, :, :2])
    return M.pck_transfer(kp, verts, faces, K, kf, kb, area, **kw)


# --------------------------------------------------------------------------------------------------
# a small moving, articulated scene: a body box and a swinging leg box, translating and turning
# --------------------------------------------------------------------------------------------------

H, W = 56, 72
F_PX = 100.0


def _rot(axis, a):
    c, s = math.cos(a), math.sin(a)
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def two_box_sequence(T=5):
    """verts (T, 16, 3), faces (24, 3), joints (T, 3, 3), K (3, 3): OpenCV camera space, y down."""
    import trimesh

    body = trimesh.creation.box(extents=(1.0, 0.4, 0.4))
    leg = trimesh.creation.box(extents=(0.2, 0.6, 0.2))
    leg_v = np.asarray(leg.vertices) + [0.0, 0.3, 0.0]  # hangs down (+y) from its hinge
    hinge = np.array([0.35, 0.2, 0.0])
    faces = np.concatenate([body.faces, leg.faces + len(body.vertices)]).astype(np.int32)
    verts, joints = [], []
    for t in range(T):
        Rl = _rot("z", 0.6 * math.sin(1.3 * t))
        obj = np.concatenate([body.vertices, leg_v @ Rl.T + hinge])
        jo = np.stack([np.zeros(3), hinge, hinge + Rl @ [0.0, 0.6, 0.0]])
        Rr, tr = _rot("y", 0.12 * t), np.array([-0.4 + 0.2 * t, -0.1, 4.0])
        verts.append(obj @ Rr.T + tr)
        joints.append(jo @ Rr.T + tr)
    K = np.array([[F_PX, 0, W / 2 - 0.5], [0, F_PX, H / 2 - 0.5], [0, 0, 1]], np.float32)
    return np.array(verts, np.float32), faces, np.array(joints, np.float32), K


def _rasterize():
    pytest.importorskip("s3o_warp.kernels.raster", reason="kernels/raster.py (rasterize) not available yet")
    from s3o_warp.kernels.raster import rasterize

    return rasterize


def _render(verts, faces, K):
    rast = _rasterize()
    T = verts.shape[0]
    with torch.no_grad():
        fi, bary, depth = rast(torch.from_numpy(verts), torch.from_numpy(faces), torch.from_numpy(np.broadcast_to(K, (T, 3, 3)).copy()),
                               image_size=(H, W))
    return fi.numpy(), bary.numpy(), depth.numpy()


def _keypoints(verts, faces, K, depth):
    """Face centroids as keypoints; visible where the render's depth at their pixel matches."""
    X = verts[:, faces].mean(axis=2)  # (T, F, 3)
    xy = M.project(X.astype(np.float64), K.astype(np.float64))
    c = np.clip(np.round(xy[..., 0]).astype(int), 0, W - 1)
    r = np.clip(np.round(xy[..., 1]).astype(int), 0, H - 1)
    d = np.take_along_axis(depth.reshape(len(verts), -1), r * W + c, axis=1)
    inside = (xy[..., 0] > -0.5) & (xy[..., 0] < W - 0.5) & (xy[..., 1] > -0.5) & (xy[..., 1] < H - 0.5)
    vis = inside & (d > 0) & (np.abs(d - X[..., 2]) < 0.03)
    return np.concatenate([xy, vis[..., None].astype(np.float64)], axis=-1)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A sequence folder (masks, keypoints.json, ground_truth/gt.npz) and two run folders."""
    verts, faces, joints, K = two_box_sequence()
    T = len(verts)
    fi, bary, depth = _render(verts, faces, K)
    kp = _keypoints(verts, faces, K, depth)
    names = [f"{t:05d}" for t in range(T)]
    root = tmp_path_factory.mktemp("metrics_scene")
    seq = root / "seq"
    (seq / "masks").mkdir(parents=True)
    for t, n in enumerate(names):
        cv2.imwrite(str(seq / "masks" / f"{n}.png"), np.where(fi[t] >= 0, 255, 0).astype(np.uint8))
    write_keypoints({"names": [f"c{f}" for f in range(len(faces))], "frames": {n: kp[t].tolist() for t, n in enumerate(names)}},
                    seq / "keypoints.json")
    (seq / "ground_truth").mkdir()
    np.savez(seq / "ground_truth" / "gt.npz", verts=verts, faces=faces, K=K, image_size=np.array([H, W]),
             joints=joints, joint_parents=np.array([-1, 0, 1]), joint_names=np.array(["body", "hip", "foot"]),
             frame_names=np.array(names))
    runs = {}
    for name, v, j in (("self", verts, joints), ("frozen", np.repeat(verts[:1], T, 0), np.repeat(joints[:1], T, 0))):
        run = root / name
        run.mkdir()
        extra = {"weights": np.repeat(np.eye(2), 8, 0)} if name == "self" else {}  # body box: bone 0, leg box: 1
        np.savez(run / "motion.npz", verts_cam=v, faces=faces, K=np.broadcast_to(K, (T, 3, 3)), image_size=np.array([H, W]),
                 frame_names=np.array(names), joints_cam=j, **extra)
        runs[name] = run
    return dict(seq=seq, runs=runs, verts=verts, faces=faces, joints=joints, K=K, fi=fi, bary=bary, kp=kp, names=names)


# --------------------------------------------------------------------------------------------------
# pure functions
# --------------------------------------------------------------------------------------------------


def test_mask_iou_hand_made():
    a = np.zeros((3, 4, 4), bool)
    b = np.zeros((3, 4, 4), bool)
    a[0, :2] = True  # 8 px
    b[0, 1:3] = True  # 8 px, 4 shared
    a[1, 0, 0] = True  # disjoint
    b[1, 3, 3] = True
    np.testing.assert_allclose(M.mask_iou(a, b), [4 / 12, 0.0, 1.0])  # frame 2: both empty
    with pytest.raises(ValueError, match="shapes differ"):
        M.mask_iou(a, b[:2])


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(50, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    dst = 2.5 * src @ R.T + [0.3, -1.0, 4.0]
    s, R2, t = M.umeyama(src, dst)
    assert s == pytest.approx(2.5, rel=1e-10)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose(t, [0.3, -1.0, 4.0], atol=1e-10)
    # a reflection is never returned
    s, R3, _ = M.umeyama(src, src * [1, 1, -1])
    assert np.linalg.det(R3) == pytest.approx(1.0)


def test_sample_surface_is_on_the_mesh_and_area_weighted():
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [3, 0, 1], [0, 2, 1]], float)  # areas 0.5 and 3
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    p = M.sample_surface(verts, faces, 20000, seed=3)
    on_first = p[:, 2] == 0
    assert np.all(on_first | (np.abs(p[:, 2] - 1) < 1e-12))
    assert on_first.mean() == pytest.approx(0.5 / 3.5, abs=0.01)
    q = p[on_first]
    assert np.all(q[:, :2] >= -1e-12) and np.all(q[:, 0] + q[:, 1] <= 1 + 1e-12)
    np.testing.assert_array_equal(p, M.sample_surface(verts, faces, 20000, seed=3))  # fixed seed


def test_chamfer_fscore_against_dense_distances():
    rng = np.random.default_rng(2)
    a, b = rng.random((300, 3)), rng.random((200, 3)) + 0.05
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)
    r = M.chamfer_fscore(a, b, threshold=0.08)
    assert r["chamfer"] == pytest.approx(0.5 * (d.min(1).mean() + d.min(0).mean()), rel=1e-12)
    prec, rec = (d.min(1) < 0.08).mean(), (d.min(0) < 0.08).mean()
    assert r["precision"] == pytest.approx(prec) and r["recall"] == pytest.approx(rec)
    assert r["fscore"] == pytest.approx(2 * prec * rec / (prec + rec))
    assert M.chamfer_fscore(a, a, 1e-3) == {"chamfer": 0.0, "precision": 1.0, "recall": 1.0, "fscore": 1.0}


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
        # one reference frame per chunk (long videos) and no pair arrays: the same counts
        rc = _fast_pckt(kp, face_index, bary, verts, faces, K, area, alpha=0.3, threshold_frame=mode,
                        chunk_elements=1, pair_limit=0)
        assert (rc["correct"], rc["total"]) == (c0, t0) and rc["pred"] is None
        np.testing.assert_array_equal(rc["per_keypoint_correct"], r["per_keypoint_correct"])
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
    face, w, px = M.surface_under_keypoints(fi, bary, np.array([[2.4, 1.6], [3.6, 2.0], [0.2, 0.4], [-9.0, -9.0]]))
    np.testing.assert_array_equal(face, [7, 8, 9, 9])
    np.testing.assert_array_equal(px, [[2, 2], [3, 2], [0, 0], [0, 0]])
    np.testing.assert_allclose(w[0], [0.2, 0.3, 0.5])
    face, _, _ = M.surface_under_keypoints(np.full((3, 3), -1), np.zeros((3, 3, 3)), np.zeros((2, 2)))
    np.testing.assert_array_equal(face, [-1, -1])


def test_alignment_recovers_a_known_similarity():
    verts, faces, joints, _ = two_box_sequence()
    s, R, t = 0.5, _rot("y", 0.12) @ _rot("z", -0.08), np.array([0.05, -0.03, 0.1])
    pred = ((verts.astype(np.float64) - t) @ R) / s  # so that s R pred + t = gt
    out, sim = M.shape_metrics(pred, faces, verts, faces, n_points=2000, icp_points=6000)
    assert sim.scale == pytest.approx(s, rel=1e-4)
    np.testing.assert_allclose(sim.rotation, R, atol=1e-4)
    np.testing.assert_allclose(sim.translation, t, atol=1e-3)
    assert out["chamfer"] < 1e-4 and out["fscore"] == 1.0
    pj = ((joints.astype(np.float64) - t) @ R) / s
    sk = M.skeleton_distance(pj, joints, M.bbox_diagonal(verts), sim)
    assert sk["distance"] < 1e-4 and (sk["gt_joints"], sk["pred_joints"]) == (3, 3)
    # without the alignment the same prediction is far off: the metric can fail
    far = M.skeleton_distance(pj, joints, M.bbox_diagonal(verts))
    assert far["distance"] > 0.5


def test_skeleton_distance_against_loops():
    rng = np.random.default_rng(5)
    gt, pr, diag = rng.random((3, 4, 3)), rng.random((3, 6, 3)), np.array([1.0, 2.0, 0.5])
    want = np.mean([np.mean([min(np.linalg.norm(g - p) for p in pr[t]) for g in gt[t]]) / diag[t] for t in range(3)])
    rev = np.mean([np.mean([min(np.linalg.norm(g - p) for g in gt[t]) for p in pr[t]]) / diag[t] for t in range(3)])
    r = M.skeleton_distance(pr, gt, diag)
    assert r["distance"] == pytest.approx(want) and r["distance_pred_to_gt"] == pytest.approx(rev)
    assert (r["gt_joints"], r["pred_joints"]) == (4, 6)


# --------------------------------------------------------------------------------------------------
# whole runs (need the rasteriser)
# --------------------------------------------------------------------------------------------------


def test_ground_truth_scored_against_itself_is_perfect(scene):
    m = M.evaluate_run(scene["runs"]["self"], scene["seq"], progress=False, n_points=2000)
    assert m["mask_iou"]["mean"] == 1.0
    assert m["pck_t"]["pck"] == 100.0 and m["pck_t"]["total"] > 40
    assert m["shape_3d"]["chamfer"] < 1e-6 and m["shape_3d"]["fscore"] == 1.0
    assert m["skeleton"]["distance"] < 1e-5
    assert (m["skeleton"]["gt_joints"], m["skeleton"]["pred_joints"]) == (3, 3)
    for key in ("limbs", "limbs_distinct"):  # the ground truth's own joints are a chain along its limb
        assert m["skeleton"][key]["covered"] == m["skeleton"][key]["total"] == 1, key
    assert m["skeleton"]["limbs_distinct"]["branch"] is False and re.search(r"of distinct joints +1/1", M.format_table(m))
    assert m["skeleton"]["limbs_framewise"]["covered"] == 1 and re.search(r"each frame aligned alone +1/1", M.format_table(m))
    assert [(o["limb"], o["bone"], o["kept"]) for o in m["limb_identity"]["limbs"]] == [("foot", 1, 1.0)]
    assert m["bones"] == {"count": 2, "empty": []} and re.search(r"bones owning no vertex +0/2", M.format_table(m))
    assert m["skipped"] == {}
    json.dumps(m)  # JSON-ready


def test_frame_similarities_take_out_each_frames_own_pose_error():
    """A prediction whose every frame is off by its own similarity: the sequence alignment cannot undo it, the
    per-frame alignments (the sequence's, then ICP on the frame alone) map its joints onto the ground truth."""
    verts, faces, joints, _ = two_box_sequence()
    T = len(verts)
    pred, pj = np.empty(verts.shape), np.empty(joints.shape)
    for t in range(T):  # x = (g - tr) @ R / s, so that s R x + tr = g; each frame its own
        s, R = 1.0 + 0.04 * (-1) ** t, _rot("y", 0.1 * math.sin(2.0 * t)) @ _rot("z", 0.05 * t)
        tr = np.array([0.2 * math.sin(t), 0.05 * t, 0.3 * math.cos(1.7 * t)])
        pred[t], pj[t] = ((verts[t] - tr) @ R) / s, ((joints[t] - tr) @ R) / s
    _, sim = M.shape_metrics(pred, faces, verts, faces, n_points=1000, icp_points=6000)
    diag = M.bbox_diagonal(verts)
    seq_err = np.linalg.norm(sim(pj) - joints, axis=-1).max(1) / diag
    sims = M.frame_similarities(pred, faces, verts, faces, sim, n_points=4000)
    err = np.stack([np.linalg.norm(f(pj[t]) - joints[t], axis=-1).max() for t, f in enumerate(sims)]) / diag
    assert seq_err.max() > 0.1 and err.max() < 0.01, (seq_err, err)
    # one similarity for every frame (no error of its own): each frame's ICP stays at the sequence's
    _, same = M.shape_metrics(pred[:1].repeat(3, 0), faces, verts[:1].repeat(3, 0), faces, n_points=1000)
    for f in M.frame_similarities(pred[:1].repeat(3, 0), faces, verts[:1].repeat(3, 0), faces, same):
        assert np.linalg.norm(f(pj[0]) - joints[0], axis=-1).max() / diag[0] < 0.01


def test_limbs_framewise_counts_the_rig_apart_from_each_frames_pose(scene, tmp_path):
    """The ground truth with every frame pushed along the camera ray by its own amount: the sequence-aligned
    count loses the leg, the per-frame reading keeps it."""
    T = len(scene["verts"])
    dz = np.array([0.0, 0.3, -0.3, 0.3, -0.3])[:T, None, None] * np.array([0, 0, 1.0])
    run = tmp_path / "jolted"
    run.mkdir()
    np.savez(run / "motion.npz", verts_cam=scene["verts"] + dz, faces=scene["faces"],
             K=np.broadcast_to(scene["K"], (T, 3, 3)), image_size=np.array([H, W]), frame_names=np.array(scene["names"]),
             joints_cam=scene["joints"] + dz)
    m = M.evaluate_run(run, scene["seq"], progress=False, n_points=1000)["skeleton"]
    assert m["limbs_distinct"]["covered"] == 0 and m["limbs_framewise"]["covered"] == 1 == m["limbs_framewise"]["total"]
    assert len(m["limbs_framewise"]["frame_scale"]) == T
    off = M.evaluate_run(run, scene["seq"], progress=False, n_points=1000, framewise_limbs=False)["skeleton"]
    assert "limbs_framewise" not in off


def test_rescore_script_scores_runs_again_beside_their_own_metrics(scene, tmp_path, capsys):
    import shutil

    main = runpy.run_path(str(REPO / "scripts" / "rescore_limbs.py"), run_name="rescore")["main"]
    run = tmp_path / "run"
    shutil.copytree(scene["runs"]["self"], run)
    before = {"skeleton": {"limbs": {"covered": 0, "total": 1, "limbs": [{"limb": "foot", "tol_needed": 0.3}]}}}
    (run / "metrics.json").write_text(json.dumps(before))
    out = tmp_path / "rescore.json"
    assert main([f"{run}:{scene['seq']}", "--out", str(out)]) == 0
    row = json.loads(out.read_text())["results"][0]
    assert row["before"]["limbs"] == {"covered": 0, "total": 1, "to_tip": False, "tol_needed": {"foot": 0.3}}
    assert row["now"]["limbs"]["covered"] == 1 and row["now"]["limbs_framewise"]["covered"] == 1  # the truth itself
    assert json.loads((run / "metrics.json").read_text()) == before  # the run's own file is left as it was
    assert (run / "metrics-rescored.json").is_file()
    assert main([str(run), "--out", str(out)]) == 2 and "RUN_DIR:SEQUENCE_DIR" in capsys.readouterr().err
    (run / "metrics.json").write_text("{not json")
    assert main([f"{run}:{scene['seq']}", "--out", str(out)]) == 2 and "not valid JSON" in capsys.readouterr().err


def test_frozen_prediction_scores_clearly_lower(scene):
    m = M.evaluate_run(scene["runs"]["frozen"], scene["seq"], progress=False, n_points=2000)
    iou = m["mask_iou"]["per_frame"]
    assert iou[scene["names"][0]] == 1.0 and m["mask_iou"]["mean"] < 0.7
    assert m["pck_t"]["pck"] < 50.0
    assert m["shape_3d"]["chamfer"] > 0.02 and m["shape_3d"]["fscore"] < 0.8
    assert m["skeleton"]["distance"] > 0.02
    assert "weights" in m["skipped"]["limb_identity"]  # this run's motion.npz has none


def test_scores_a_synth_sequence(tmp_path):
    """What s3o_warp.synth writes (ground_truth/ground_truth.npz, no frame names) is read and scored."""
    synth = pytest.importorskip("s3o_warp.synth")
    _rasterize()
    seq = synth.make_sequence(tmp_path / "seq", frames=5, size=(80, 64), progress=False)
    gt = M.load_ground_truth(seq / "ground_truth")
    assert gt.frame_names is None and gt.joints is not None
    names = np.array(sorted(p.stem for p in (seq / "masks").iterdir()))
    scores = {}
    for name, sel in (("self", np.arange(5)), ("frozen", np.zeros(5, int))):
        run = tmp_path / name
        run.mkdir()
        np.savez(run / "motion.npz", verts_cam=gt.verts[sel], faces=gt.faces, K=gt.K, image_size=np.array(gt.image_size),
                 frame_names=names, joints_cam=gt.joints[sel])
        scores[name] = M.evaluate_run(run, seq, progress=False, n_points=1000)
    good, bad = scores["self"], scores["frozen"]
    assert good["mask_iou"]["mean"] == 1.0 and good["pck_t"]["pck"] == 100.0
    assert sorted(good["skipped"]) == ["bones", "limb_identity"]  # these motion.npz files carry no skinning weights
    assert good["shape_3d"]["chamfer"] < 1e-6 and good["shape_3d"]["fscore"] == 1.0 and good["skeleton"]["distance"] < 1e-5
    assert bad["mask_iou"]["mean"] < 0.9 and bad["shape_3d"]["fscore"] < 0.9 and bad["skeleton"]["distance"] > 0.01
    assert bad["pck_t"]["pck"] < good["pck_t"]["pck"]


def test_pck_of_a_run_matches_naive_loops(scene):
    """evaluate_run's PCK-T (chunked renders, KD-tree lookups) equals the loop twin on full renders."""
    kp, fi, verts, faces = scene["kp"], scene["fi"], scene["verts"], scene["faces"]
    T = len(verts)
    area = (fi >= 0).reshape(T, -1).sum(1)
    K = np.broadcast_to(scene["K"], (T, 3, 3)).astype(np.float64)
    frozen = np.repeat(verts[:1], T, 0)
    for run, v in (("self", verts), ("frozen", frozen)):
        fi_p, bary_p, _ = _render(v, faces, scene["K"])
        c0, t0, _ = naive_pckt(kp, fi_p, bary_p, v, faces, K, area)
        m = M.evaluate_run(scene["runs"][run], scene["seq"], progress=False, chunk=2, n_points=500)
        assert (m["pck_t"]["correct"], m["pck_t"]["total"]) == (c0, t0)


def _evaluate_main():
    """``main`` of scripts/evaluate.py, run in this process (no second torch/Warp start-up)."""
    return runpy.run_path(str(REPO / "scripts" / "evaluate.py"), run_name="evaluate")["main"]


def test_evaluate_script_writes_metrics_json(scene, tmp_path, capsys):
    out = tmp_path / "m.json"
    rc = _evaluate_main()([str(scene["runs"]["frozen"] / "motion.npz"), "--sequence", str(scene["seq"]), "--out", str(out),
                           "--points", "500"])
    printed = capsys.readouterr().out
    assert rc == 0 and "PCK-T" in printed and "mask IoU" in printed and "F-score" in printed
    m = json.loads(out.read_text())
    assert 0 < m["mask_iou"]["mean"] < 1 and not list(tmp_path.glob("*.tmp"))
    # default destination: metrics.json inside the run directory
    run = tmp_path / "run"
    run.mkdir()
    (run / "motion.npz").write_bytes((scene["runs"]["self"] / "motion.npz").read_bytes())
    assert _evaluate_main()([str(run), "--sequence", str(scene["seq"]), "--points", "500"]) == 0
    assert json.loads((run / "metrics.json").read_text())["pck_t"]["pck"] == 100.0


# --------------------------------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------------------------------


def _motion(path, **over):
    T = 2
    d = dict(verts_cam=np.ones((T, 3, 3), np.float32), faces=np.array([[0, 1, 2]], np.int32), K=np.eye(3, dtype=np.float32),
             image_size=np.array([4, 5]), frame_names=np.array(["a", "b"]))
    d.update(over)
    d = {k: v for k, v in d.items() if v is not None}
    np.savez(path, **d)
    return path


def test_bad_prediction_files(tmp_path):
    with pytest.raises(InputError, match="motion.npz.*not found"):
        M.load_predictions(tmp_path)
    with pytest.raises(InputError, match="no such USD file"):
        M.load_predictions(tmp_path / "run.usda")
    with pytest.raises(InputError, match="missing key 'frame_names'"):
        M.load_predictions(_motion(tmp_path / "a.npz", frame_names=None))
    with pytest.raises(InputError, match=r"'verts_cam' must have shape \(T, N, 3\)"):
        M.load_predictions(_motion(tmp_path / "b.npz", verts_cam=np.ones((2, 3), np.float32)))
    with pytest.raises(InputError, match="'faces' index vertices outside"):
        M.load_predictions(_motion(tmp_path / "c.npz", faces=np.array([[0, 1, 5]])))
    with pytest.raises(InputError, match="3 entries but 'verts_cam' has 2"):
        M.load_predictions(_motion(tmp_path / "d.npz", frame_names=np.array(["a", "b", "c"])))
    with pytest.raises(InputError, match="object arrays"):
        M.load_predictions(_motion(tmp_path / "e.npz", frame_names=np.array(["a", "b"], dtype=object)))
    with pytest.raises(InputError, match="'K' must have shape"):
        M.load_predictions(_motion(tmp_path / "f.npz", K=np.eye(4)))
    (tmp_path / "g.npz").write_text("not a zip")
    with pytest.raises(InputError, match="not a readable .npz"):
        M.load_predictions(tmp_path / "g.npz")
    p = M.load_predictions(_motion(tmp_path / "ok.npz"))
    assert p.K.shape == (2, 3, 3) and p.frame_names == ["a", "b"] and p.joints_cam is None


def test_bad_sequence_files(tmp_path):
    run = _motion(tmp_path / "motion.npz")
    (tmp_path / "seq" / "masks").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "seq" / "masks" / "a.png"), np.zeros((4, 6), np.uint8))
    with pytest.raises(InputError, match=r"a\.png: mask is 6x4 but the prediction's frames are 5x4"):
        M.evaluate_run(run, tmp_path / "seq", progress=False)
    cv2.imwrite(str(tmp_path / "seq" / "masks" / "a.png"), np.zeros((4, 5), np.uint8))
    with pytest.raises(InputError, match=r"b\.png: mask not found"):
        M.evaluate_run(run, tmp_path / "seq", progress=False)
    with pytest.raises(InputError, match="sequence folder not found"):
        M.evaluate_run(run, tmp_path / "nope", progress=False)
    (tmp_path / "kp.json").write_text("{broken")
    with pytest.raises(InputError, match="kp.json: not valid JSON"):
        M.load_keypoints(tmp_path / "kp.json")
    (tmp_path / "kp.json").write_text(json.dumps({"names": ["x"], "frames": {"a": [[1, 2, 1]], "b": [[1, 2, 1], [3, 4, 0]]}}))
    with pytest.raises(InputError, match="different keypoint counts"):
        M.load_keypoints(tmp_path / "kp.json")
    np.savez(tmp_path / "gt.npz", verts=np.ones((3, 3, 3)), faces=np.array([[0, 1, 2]]))
    with pytest.raises(InputError, match="has 3 frames and no frame_names"):
        M._pair_frames(["a", "b"], M.load_ground_truth(tmp_path / "gt.npz"), run)
    np.savez(tmp_path / "gt2.npz", faces=np.array([[0, 1, 2]]))
    with pytest.raises(InputError, match="missing key 'verts'"):
        M.load_ground_truth(tmp_path / "gt2.npz")


def test_ground_truth_drops_non_deforming_joints(tmp_path):
    np.savez(tmp_path / "gt.npz", verts=np.ones((2, 3, 3)), faces=np.array([[0, 1, 2]]), joints=np.arange(18.0).reshape(2, 3, 3),
             joint_names=np.array(["a", "ik", "b"]), joint_deforming=np.array([True, False, True]))
    gt = M.load_ground_truth(tmp_path)
    assert gt.joints.shape == (2, 2, 3) and gt.joint_names == ["a", "b"]
    np.testing.assert_array_equal(gt.joints[:, 1], np.arange(18.0).reshape(2, 3, 3)[:, 2])


def test_ground_truth_reads_end_joints_tips(tmp_path):
    verts = np.arange(2 * 4 * 3, dtype=np.float32).reshape(2, 4, 3)
    np.savez(tmp_path / "gt.npz", verts=verts, faces=np.array([[0, 1, 2]]), joints=np.zeros((2, 3, 3)),
             joint_names=np.array(["a", "ik", "b"]), joint_deforming=np.array([True, False, True]),
             keypoint_names=np.array(["b_tip", "ik_tip", "a", "zz_tip"]), keypoint_vertex=np.array([3, 1, 0, 2]))
    gt = M.load_ground_truth(tmp_path)
    assert list(gt.tips) == ["b"]  # a kept joint's tip; not a dropped joint's, a plain keypoint or an unknown name
    np.testing.assert_array_equal(gt.tips["b"], verts[:, 3])
    np.savez(tmp_path / "gt.npz", verts=verts, faces=np.array([[0, 1, 2]]), joints=np.zeros((2, 1, 3)),
             joint_names=np.array(["b"]), keypoint_names=np.array(["b_tip"]), keypoint_vertex=np.array([4]))
    with pytest.raises(InputError, match="'b_tip' names vertex 4, but there are 4"):
        M.load_ground_truth(tmp_path)


def test_limb_coverage_goes_on_to_the_end_joints_tip():
    from s3o_warp.evaluation.metrics import limb_coverage

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


def test_evaluate_script_bad_input_is_one_line(tmp_path, capsys):
    assert _evaluate_main()([str(tmp_path / "x.usdc"), "--sequence", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.strip().count("\n") == 0 and "no such USD file" in err
    r = subprocess.run([sys.executable, str(REPO / "scripts" / "evaluate.py"), str(tmp_path), "--sequence", str(tmp_path)],
                       capture_output=True, text=True, timeout=120)  # the real command line, no torch needed to fail
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "motion.npz" in r.stderr


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
    from scipy.ndimage import distance_transform_edt

    src = shared_data / "badja" / f"{animal}.json"
    masks = shared_data / "davis" / "Annotations" / "480p" / animal
    if not src.exists() or not masks.is_dir():
        pytest.skip(f"{src} or {masks} not in the shared data")
    out = tmp_path / "keypoints.json"
    from s3o_warp.data.keypoints import main

    assert main([str(src), str(out), "--frames", str(shared_data / "davis" / "JPEGImages" / "480p" / animal)]) == 0
    kp = M.load_keypoints(out)
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


def test_empty_bones_are_the_largest_weight_of_no_vertex():
    W = np.array([[0.6, 0.3, 0.1, 0.0], [0.2, 0.7, 0.1, 0.0], [0.5, 0.1, 0.4, 0.0]])  # bone 2 weighs, owns nothing
    assert M.empty_bones(W) == {"count": 4, "empty": [2, 3]}
    assert M.empty_bones(W[:, :2]) == {"count": 2, "empty": []}
    with pytest.raises(ValueError, match="empty_bones"):
        M.empty_bones(W[0])


def test_joints_inside_a_moving_box():
    import trimesh

    box = trimesh.creation.box(extents=(2.0, 1.0, 1.0))
    V0 = np.asarray(box.vertices)
    shift = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 3.0]])  # two frames, the box moves
    verts = V0[None] + shift[:, None]
    # joint 0 inside in both frames; joint 1 inside at frame 0, 0.25 outside (along y) at frame 1
    joints = np.array([[[0.2, 0.1, 0.0], [0.0, 0.3, 0.0]], [[0.7, 0.1, 3.0], [0.5, 0.75, 3.0]]])
    r = M.joints_inside(joints, verts, box.faces)
    assert r["fraction"] == pytest.approx(3 / 4)
    assert r["per_joint"] == pytest.approx([1.0, 0.5])
    assert r["max_outside"] == pytest.approx(0.25, abs=1e-5)
    with pytest.raises(ValueError, match="joints_inside"):
        M.joints_inside(joints[:1], verts, box.faces)


def test_limb_coverage_on_a_hand_made_tree():
    from s3o_warp.evaluation.metrics import gt_limbs, limb_coverage

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
    from s3o_warp.evaluation.metrics import Similarity, limb_identity

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


def test_a_usd_export_scores_like_its_run(tmp_path):
    """scripts/evaluate.py on an exported USD: the same IoU and PCK-T as on the run directory."""
    from s3o_warp.export.rig import Rig, save_rig
    from s3o_warp.export.usd import export_usd

    synth = pytest.importorskip("s3o_warp.synth")
    seq = synth.make_sequence(tmp_path / "seq", frames=5, size=(80, 64), progress=False)
    gt = np.load(seq / "ground_truth" / "ground_truth.npz")
    T, V = gt["verts"].shape[:2]
    K = np.broadcast_to(gt["K"], (T, 3, 3)) if gt["K"].ndim == 2 else gt["K"]
    # a one-bone rig whose root carries the ground-truth motion exactly: rest = frame 0, root = identity
    rig = Rig(verts=gt["verts"][0], faces=gt["faces"], colors=np.full((V, 3), 0.5, np.float32),
              weights=np.ones((V, 1), np.float32), bone_names=["bone_00"], parents=np.array([-1]),
              bind=np.eye(4)[None], bone_motion=np.tile(np.eye(4), (T, 1, 1, 1)), root=np.tile(np.eye(4), (T, 1, 1)),
              K=np.asarray(K, np.float64), image_size=tuple(int(x) for x in gt["image_size"]), fps=10.0,
              frame_names=sorted(p.stem for p in (seq / "masks").glob("*.png")))
    run = tmp_path / "run"
    save_rig(run, rig)
    usd = export_usd(rig, run / "x.usda", influences=1).path
    a = M.evaluate_run(run, seq, progress=False)
    b = M.evaluate_run(usd, seq, progress=False)
    assert a["mask_iou"]["mean"] > 0.2  # a real score, not an empty render
    assert b["mask_iou"]["mean"] == pytest.approx(a["mask_iou"]["mean"], abs=1e-3)
    assert b["pck_t"]["pck"] == pytest.approx(a["pck_t"]["pck"], abs=0.5)
    assert b["frames"] == a["frames"] == T
