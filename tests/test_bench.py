"""The fit benchmark's JSON: rows merge across invocations, reruns replace their own row, history stays."""

from __future__ import annotations

import json
import sys
from multiprocessing import get_context
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import bench_fit  # noqa: E402


def _entry(**over):
    e = dict(case="horse", method="s3o", seed=0, preset="default", overrides=[], git_commit="a" * 40, pck_t=80.0)
    e.update(over)
    return e


def _write_rows(dest, seed, n):
    for k in range(n):
        bench_fit.record(Path(dest), {"command": f"seed {seed}"}, _entry(seed=seed, pck_t=float(k)))


def test_record_replaces_a_rerun_and_keeps_other_commits(tmp_path):
    dest = tmp_path / "fit-cpu.json"
    bench_fit.record(dest, {"command": "first"}, _entry())
    bench_fit.record(dest, {"command": "second"}, _entry(seed=1))
    bench_fit.record(dest, {"command": "rerun"}, _entry(pck_t=81.0))  # same fit, same commit: replaced
    bench_fit.record(dest, {"command": "later"}, _entry(git_commit="b" * 40, pck_t=82.0))  # another commit: kept
    doc = json.loads(dest.read_text())
    assert doc["command"] == "later"
    rows = sorted((r["seed"], r["git_commit"][0], r["pck_t"]) for r in doc["results"])
    assert rows == [(0, "a", 81.0), (0, "b", 82.0), (1, "a", 80.0)]
    assert not [p.name for p in tmp_path.iterdir() if ".tmp" in p.name]  # no temporary file left


def test_record_from_processes_side_by_side_keeps_every_row(tmp_path):
    dest = tmp_path / "fit-cpu.json"
    ctx = get_context("spawn")
    procs = [ctx.Process(target=_write_rows, args=(str(dest), seed, 15)) for seed in range(3)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
        assert p.exitcode == 0
    rows = json.loads(dest.read_text())["results"]
    assert sorted((r["seed"], r["pck_t"]) for r in rows) == [(s, 14.0) for s in range(3)]


def test_a_tagged_t_o_study_does_not_overwrite_the_sequences_figure():
    plain, tagged = bench_fit.figure_path("horse", "cpu"), bench_fit.figure_path("horse", "cpu", "body")
    assert plain.name == "skeleton_t_o-horse-cpu.png" and tagged.name == "skeleton_t_o-horse-body-cpu.png"
    assert plain.parent == tagged.parent == bench_fit.REPO / "renders"


def test_a_rows_resamplings_say_which_were_used_and_how(tmp_path):
    recs = [{"phase": "joint", "step": 1, "seconds": 1.0},
            {"phase": "eval", "what": "resample", "vertices_before": 1200, "vertices_after": 1180, "kept": False,
             "method": "marching"},
            {"phase": "eval", "what": "resample", "vertices_before": 1180, "vertices_after": 1180, "kept": True,
             "method": None},
            {"phase": "eval", "what": "resample", "vertices_before": 1180, "vertices_after": 1210, "kept": False,
             "method": "isotropic"}]
    (tmp_path / "log.jsonl").write_text("\n".join(json.dumps(r) for r in recs) + "\n")
    assert bench_fit.resamplings(tmp_path) == ["1200->1180 marching", "1180->1180 refused", "1180->1210 isotropic"]


def test_bench_flows_true_flow_is_the_surface_points_motion():
    """bench_flow's reference: each foreground pixel's surface point, carried to the next frame and projected.
    A square facing the camera moves across and away: the flow is that of the back-projected pixel centres."""
    import bench_flow
    import numpy as np

    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    sq = np.array([[-0.4, -0.3, 4.0], [0.4, -0.3, 4.0], [0.4, 0.3, 4.0], [-0.4, 0.3, 4.0]])
    d = np.array([0.05, -0.02, 0.3])
    verts = np.stack([sq, sq + d]).astype(np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    (flow, fg), = bench_flow.true_frame_flow(verts, faces, np.stack([K, K]).astype(np.float32), (48, 64))
    assert fg.sum() == 20 * 15  # 0.8 x 0.6 at depth 4, focal 100
    r, c = np.nonzero(fg)
    X = np.stack([(c - K[0, 2]) / K[0, 0], (r - K[1, 2]) / K[1, 1], np.ones(len(r))], -1) * 4.0 + d
    want = np.stack([K[0, 0] * X[:, 0] / X[:, 2] + K[0, 2] - c, K[1, 1] * X[:, 1] / X[:, 2] + K[1, 2] - r], -1)
    np.testing.assert_allclose(flow[r, c], want, atol=1e-3)
    assert np.abs(want[:, 0]).max() > 1.0 and np.ptp(want[:, 0]) > 1.0  # moves, and not as one translation
    assert not flow[~fg].any()


def test_git_commit_outside_a_checkout(tmp_path, monkeypatch):
    """S3O_GIT_COMMIT names the commit of a copied tree (a lent GPU machine: no .git, or a stale one); else None outside a checkout."""
    from s3o_warp import provenance

    monkeypatch.setattr(provenance, "REPO", tmp_path)
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path.parent))
    monkeypatch.delenv("S3O_GIT_COMMIT", raising=False)
    assert provenance.git_commit() is None
    monkeypatch.setenv("S3O_GIT_COMMIT", "c" * 40)
    assert provenance.git_commit() == "c" * 40
    monkeypatch.setattr(provenance, "REPO", Path(__file__).resolve().parents[1])  # a checkout: the variable still wins
    assert provenance.git_commit() == "c" * 40


def test_other_body_plans_are_cases():
    assert {"robot", "lizard"} <= set(bench_fit.SYNTH) and "dance-twirl" in bench_fit.DAVIS
    assert bench_fit.SYNTH["robot"]["clip"] == "Walking" and bench_fit.SYNTH["lizard"]["source"] == "lizard"
    front = bench_fit.SYNTH["robot-dance"]  # the biped from the front: an orbit about azimuth 90 (0 is its side)
    assert front["clip"] == "Dance" and sum(front["azim"]) / 2 == 90.0


def test_a_davis_case_without_keypoints_opens(shared_data, tmp_path, monkeypatch):
    """dance-twirl has masks and no BADJA keypoints: the case opens as a sequence, with no keypoints.json."""
    from s3o_warp.data.sequence import open_sequence

    monkeypatch.setattr(bench_fit, "DATA", shared_data)
    seq = bench_fit.prepare_case("dance-twirl", tmp_path)
    assert not (seq / "keypoints.json").exists()
    assert len(open_sequence(seq).frame_names) == 90
    assert (bench_fit.prepare_case("dog", tmp_path) / "keypoints.json").is_file()  # BADJA's still converted


def test_a_rows_views_figures_carry_the_turn_error():
    """bench_fit's row takes metrics.json's turn error (the summary, not the per-frame list) beside novel-view IoU."""
    view = {"mean": 0.8, "per_view": {"top": 0.7, "front": 0.8, "side": 0.9}}
    turn = {"mean_deg": 6.0, "max_deg": 12.5, "end_deg": 12.5, "drift_vertical_deg": -12.4, "end_vertical_deg": -12.0,
            "per_frame_deg": [0.5, 12.5], "vertical_deg": [0.4, -12.0], "frames": 2}
    metrics = {"views": {"sequence": view, "framewise": view, "turn_error": turn},
               "surface": {"fscore": {"1%": 0.3, "2%": 0.6}, "normal_consistency": 0.9,
                           "roughness": {"pred": 0.1, "truth": 0.05, "angle_deg": 60.0}}}
    row = bench_fit.views_figures(metrics)
    assert row["turn_error"] == {"mean_deg": 6.0, "max_deg": 12.5, "end_deg": 12.5, "end_vertical_deg": -12.0,
                                 "drift_vertical_deg": -12.4}
    assert row["novel_iou"]["framewise"]["side"] == 0.9
    del metrics["views"]["turn_error"]  # a metrics.json from before it: no figure, no error
    assert "turn_error" not in bench_fit.views_figures(metrics)


def test_a_rows_keypoint_figures_split_the_limbs_ends_and_sides():
    """bench_fit's row takes PCK-T by role from metrics.json's groups, and the limbs' swap fraction."""
    groups = {"ends": {"pck": 60.0}, "rest": {"pck": 90.0}, "near": {"pck": 85.0}, "far": {"pck": 70.0},
              "worst": {"keypoint": "foot_bl", "pck": 12.5}}
    row = bench_fit.keypoint_figures({"pck_t": {"pck": 80.0, "groups": groups}, "limb_identity": {"mean_swapped": 0.1}})
    assert row == {"pck_t_ends": 60.0, "pck_t_rest": 90.0, "pck_t_near": 85.0, "pck_t_far": 70.0,
                   "pck_t_worst": {"keypoint": "foot_bl", "pck": 12.5}, "swapped": 0.1}
    assert bench_fit.keypoint_figures({"pck_t": {"pck": 80.0}}) == {}  # no keypoint roles: no figures
