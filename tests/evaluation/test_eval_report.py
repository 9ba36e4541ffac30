"""A whole run scored (s3o_warp.evaluation.report and scripts/evaluate.py): a small moving two-box sequence, built and
rendered here, scored against itself (the perfect scores) and against a prediction frozen at its first frame
(clearly worse); PCK-T of a run against the loop twin; a synthetic sequence and a USD export scored; bad inputs."""

from __future__ import annotations

import json
import re
import runpy
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from eval_scene import H, W, cam_from_world, naive_pckt, tiny_motion, two_box_sequence
from s3o_warp.kernels.raster import rasterize

from s3o_warp.data.keypoints import write_keypoints
from s3o_warp.errors import InputError
from s3o_warp.evaluation.loaders import load_ground_truth
from s3o_warp.evaluation.report import _pair_frames, evaluate_run, format_table
from s3o_warp.export.rig import Rig, save_rig
from s3o_warp.export.usd import export_usd
from s3o_warp.geometry import project_np
from s3o_warp.synth.sequence import make_sequence

REPO = Path(__file__).resolve().parents[2]


def _render(verts, faces, K):
    T = verts.shape[0]
    with torch.no_grad():
        fi, bary, depth = rasterize(torch.from_numpy(verts), torch.from_numpy(faces), torch.from_numpy(np.broadcast_to(K, (T, 3, 3)).copy()),
                               image_size=(H, W))
    return fi.numpy(), bary.numpy(), depth.numpy()


def _keypoints(verts, faces, K, depth):
    """Face centroids as keypoints; visible where the render's depth at their pixel matches."""
    X = verts[:, faces].mean(axis=2)  # (T, F, 3)
    xy = project_np(X.astype(np.float64), K.astype(np.float64))
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
             frame_names=np.array(names), cam_from_world=cam_from_world(T))
    runs = {}
    for name, v, j in (("self", verts, joints), ("frozen", np.repeat(verts[:1], T, 0), np.repeat(joints[:1], T, 0))):
        run = root / name
        run.mkdir()
        extra = {"weights": np.repeat(np.eye(2), 8, 0)} if name == "self" else {}  # body box: bone 0, leg box: 1
        np.savez(run / "motion.npz", verts_cam=v, faces=faces, K=np.broadcast_to(K, (T, 3, 3)), image_size=np.array([H, W]),
                 frame_names=np.array(names), joints_cam=j, **extra)
        runs[name] = run
    return dict(seq=seq, runs=runs, verts=verts, faces=faces, joints=joints, K=K, fi=fi, bary=bary, kp=kp, names=names)


def test_ground_truth_scored_against_itself_is_perfect(scene):
    m = evaluate_run(scene["runs"]["self"], scene["seq"], progress=False, n_points=2000)
    assert m["mask_iou"]["mean"] == 1.0
    assert m["pck_t"]["pck"] == 100.0 and m["pck_t"]["total"] > 40
    assert m["shape_3d"]["chamfer"] < 1e-6 and m["shape_3d"]["fscore"] == 1.0
    assert m["skeleton"]["distance"] < 1e-5
    assert (m["skeleton"]["gt_joints"], m["skeleton"]["pred_joints"]) == (3, 3)
    for key in ("limbs", "limbs_distinct"):  # the ground truth's own joints are a chain along its limb
        assert m["skeleton"][key]["covered"] == m["skeleton"][key]["total"] == 1, key
    assert m["skeleton"]["limbs_distinct"]["branch"] is False and re.search(r"of distinct joints +1/1", format_table(m))
    assert m["skeleton"]["limbs_framewise"]["covered"] == 1 and re.search(r"each frame aligned alone +1/1", format_table(m))
    assert [(o["limb"], o["bone"], o["kept"]) for o in m["limb_identity"]["limbs"]] == [("foot", 1, 1.0)]
    assert m["bones"] == {"count": 2, "empty": []} and re.search(r"bones owning no vertex +0/2", format_table(m))
    for k in ("sequence", "framewise"):
        assert m["views"][k]["mean"] == 1.0 and sorted(m["views"][k]["per_view"]) == ["front", "side", "top"]
    assert m["surface"]["fscore"] == {"1%": 1.0, "2%": 1.0} and m["surface"]["normal_consistency"] > 0.999
    assert m["surface"]["roughness"]["pred"] == m["surface"]["roughness"]["truth"]
    assert re.search(r"novel-view IoU \(framewise\) +1\.0000", format_table(m))
    turn = m["views"]["turn_error"]
    assert turn["max_deg"] < 1e-3 and turn["frames"] == len(turn["per_frame_deg"]) == len(turn["vertical_deg"]) == 5
    assert re.search(r"turn error \(deg\) +0\.0 / 0\.0 / 0\.0 ", format_table(m))
    assert m["skipped"] == {}
    json.dumps(m)  # JSON-ready


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
    m = evaluate_run(run, scene["seq"], progress=False, n_points=1000)["skeleton"]
    assert m["limbs_distinct"]["covered"] == 0 and m["limbs_framewise"]["covered"] == 1 == m["limbs_framewise"]["total"]
    assert len(m["limbs_framewise"]["frame_scale"]) == T
    off = evaluate_run(run, scene["seq"], progress=False, n_points=1000, framewise_limbs=False)["skeleton"]
    assert "limbs_framewise" not in off


def test_a_prediction_turning_against_the_truth_reads_its_turn(scene, tmp_path):
    """The truth turned 3 t degrees about the vertical (through each frame's centroid) in frame t: metrics.json's
    turn error reads the turn from frame to frame and from the first frame to the last, and the table shows it."""
    T, k = len(scene["verts"]), 3.0
    c2w = load_ground_truth(scene["seq"] / "ground_truth").cam_from_world
    turned = np.empty(scene["verts"].shape, np.float32)
    for t, v in enumerate(scene["verts"].astype(np.float64)):
        R = Rotation.from_rotvec(np.radians(k * t) * (c2w[t, :3, :3] @ [0.0, 1.0, 0.0])).as_matrix()
        turned[t] = (v - v.mean(0)) @ R.T + v.mean(0)
    run = tmp_path / "turned"
    run.mkdir()
    np.savez(run / "motion.npz", verts_cam=turned, faces=scene["faces"], K=np.broadcast_to(scene["K"], (T, 3, 3)),
             image_size=np.array([H, W]), frame_names=np.array(scene["names"]))
    m = evaluate_run(run, scene["seq"], progress=False, n_points=1000)
    turn = m["views"]["turn_error"]
    vertical = np.array(turn["vertical_deg"])
    assert np.diff(vertical) == pytest.approx([k] * (T - 1), abs=0.5)
    assert turn["drift_vertical_deg"] == pytest.approx(k * (T - 1), abs=0.5)
    # the sequence's one alignment of the moving boxes sits somewhere in the turn, with a little tilt of its own
    assert (turn["end_deg"], turn["end_vertical_deg"]) == (turn["per_frame_deg"][-1], vertical[-1])
    assert 0 < turn["end_vertical_deg"] <= turn["end_deg"] < k * (T - 1)
    assert (np.array(turn["per_frame_deg"]) >= np.abs(vertical) - 1e-9).all()
    row = re.search(r"turn error \(deg\) +([0-9.]+) / ([0-9.]+) / ([0-9.]+) .*about the vertical \+([0-9.]+) at the "
                    r"end, \+([0-9.]+) from the first frame", format_table(m))
    assert row and float(row[3]) == pytest.approx(turn["end_deg"], abs=0.05)
    assert float(row[5]) == pytest.approx(turn["drift_vertical_deg"], abs=0.05)


def test_rescore_script_scores_runs_again_beside_their_own_metrics(scene, tmp_path, capsys):
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
    m = evaluate_run(scene["runs"]["frozen"], scene["seq"], progress=False, n_points=2000)
    iou = m["mask_iou"]["per_frame"]
    assert iou[scene["names"][0]] == 1.0 and m["mask_iou"]["mean"] < 0.7
    assert m["pck_t"]["pck"] < 50.0
    assert m["shape_3d"]["chamfer"] > 0.02 and m["shape_3d"]["fscore"] < 0.8
    assert m["skeleton"]["distance"] > 0.02
    assert m["views"]["sequence"]["mean"] < 0.6 and m["views"]["framewise"]["mean"] < 0.97
    assert m["views"]["sequence"]["mean"] < m["views"]["framewise"]["mean"]
    assert "weights" in m["skipped"]["limb_identity"]  # this run's motion.npz has none


def test_scores_a_synth_sequence(tmp_path):
    """What s3o_warp.synth writes (ground_truth/ground_truth.npz, no frame names) is read and scored."""
    seq = make_sequence(tmp_path / "seq", frames=5, size=(80, 64), progress=False)
    gt = load_ground_truth(seq / "ground_truth")
    assert gt.frame_names is None and gt.joints is not None
    names = np.array(sorted(p.stem for p in (seq / "masks").iterdir()))
    scores = {}
    for name, sel in (("self", np.arange(5)), ("frozen", np.zeros(5, int))):
        run = tmp_path / name
        run.mkdir()
        np.savez(run / "motion.npz", verts_cam=gt.verts[sel], faces=gt.faces, K=gt.K, image_size=np.array(gt.image_size),
                 frame_names=names, joints_cam=gt.joints[sel])
        scores[name] = evaluate_run(run, seq, progress=False, n_points=1000)
    good, bad = scores["self"], scores["frozen"]
    assert good["mask_iou"]["mean"] == 1.0 and good["pck_t"]["pck"] == 100.0
    assert sorted(good["skipped"]) == ["bones", "limb_identity"]  # these motion.npz files carry no skinning weights
    assert good["shape_3d"]["chamfer"] < 1e-6 and good["shape_3d"]["fscore"] == 1.0 and good["skeleton"]["distance"] < 1e-5
    assert bad["mask_iou"]["mean"] < 0.9 and bad["shape_3d"]["fscore"] < 0.9 and bad["skeleton"]["distance"] > 0.01
    assert bad["pck_t"]["pck"] < good["pck_t"]["pck"]
    g = good["pck_t"]["groups"]  # the quadruped's feet apart from the rest; its sides from the true depths
    assert g["facing_from"] == "ground truth" and g["frames_with_side"] == 5
    assert g["ends"]["keypoints"] == ["foot_fl", "foot_fr", "foot_bl", "foot_br"]
    assert g["ends"]["pck"] == g["rest"]["pck"] == g["near"]["pck"] == g["far"]["pck"] == 100.0
    assert g["ends"]["total"] + g["rest"]["total"] == good["pck_t"]["total"]
    sided = sum(v["total"] for n, v in good["pck_t"]["per_keypoint"].items() if n[-1] in "lr" and "_" in n)
    assert g["near"]["total"] + g["far"]["total"] == sided and g["near"]["total"] > 0 and g["far"]["total"] > 0
    assert bad["pck_t"]["groups"]["worst"]["pck"] < 100.0
    assert good["views"]["sequence"]["mean"] == good["views"]["framewise"]["mean"] == 1.0
    assert bad["views"]["sequence"]["mean"] < 0.9


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
        m = evaluate_run(scene["runs"][run], scene["seq"], progress=False, chunk=2, n_points=500)
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


def test_bad_sequence_files(tmp_path):
    run = tiny_motion(tmp_path / "motion.npz")
    (tmp_path / "seq" / "masks").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "seq" / "masks" / "a.png"), np.zeros((4, 6), np.uint8))
    with pytest.raises(InputError, match=r"a\.png: mask is 6x4 but the prediction's frames are 5x4"):
        evaluate_run(run, tmp_path / "seq", progress=False)
    cv2.imwrite(str(tmp_path / "seq" / "masks" / "a.png"), np.zeros((4, 5), np.uint8))
    with pytest.raises(InputError, match=r"b\.png: mask not found"):
        evaluate_run(run, tmp_path / "seq", progress=False)
    with pytest.raises(InputError, match="sequence folder not found"):
        evaluate_run(run, tmp_path / "nope", progress=False)
    np.savez(tmp_path / "gt.npz", verts=np.ones((3, 3, 3)), faces=np.array([[0, 1, 2]]))
    with pytest.raises(InputError, match="has 3 frames and no frame_names"):
        _pair_frames(["a", "b"], load_ground_truth(tmp_path / "gt.npz"), run)


def test_evaluate_script_bad_input_is_one_line(tmp_path, capsys):
    assert _evaluate_main()([str(tmp_path / "x.usdc"), "--sequence", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.strip().count("\n") == 0 and "no such USD file" in err
    r = subprocess.run([sys.executable, str(REPO / "scripts" / "evaluate.py"), str(tmp_path), "--sequence", str(tmp_path)],
                       capture_output=True, text=True, timeout=120)  # the real command line
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "motion.npz" in r.stderr


def test_a_usd_export_scores_like_its_run(tmp_path):
    """scripts/evaluate.py on an exported USD: the same IoU and PCK-T as on the run directory."""
    seq = make_sequence(tmp_path / "seq", frames=5, size=(80, 64), progress=False)
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
    a = evaluate_run(run, seq, progress=False)
    b = evaluate_run(usd, seq, progress=False)
    assert a["mask_iou"]["mean"] > 0.2  # a real score, not an empty render
    assert b["mask_iou"]["mean"] == pytest.approx(a["mask_iou"]["mean"], abs=1e-3)
    assert b["pck_t"]["pck"] == pytest.approx(a["pck_t"]["pck"], abs=0.5)
    assert b["frames"] == a["frames"] == T
