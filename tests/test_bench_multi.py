"""The multi-video benchmark: its cases render into their folders (a mirrored video made from its original), a missing
model skips the case, and a row's figures and means come from the fit's metrics."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import bench_multi  # noqa: E402

from s3o_warp.synth import make_sequence  # noqa: E402


@pytest.fixture
def renders(tmp_path, monkeypatch):
    """bench_multi with every model present (empty files) and a fake renderer: the built-in quadruped, 3 frames at
    64x48, whatever the case asks for; the calls are kept."""
    data = tmp_path / "data"
    for spec in (s for case in bench_multi.CASES.values() for s in case["videos"].values() if "source" in s):
        (data / spec["source"]).parent.mkdir(parents=True, exist_ok=True)
        (data / spec["source"]).touch()
    monkeypatch.setattr(bench_multi, "DATA", data)
    calls = []

    def fake(out, **spec):
        calls.append((Path(out), spec))
        return make_sequence(out, source="quadruped", frames=3, size=(64, 48), progress=False)

    monkeypatch.setattr(bench_multi, "make_sequence", fake)
    return data, calls


def test_the_cases_are_the_benchmarks_shots():
    robot = bench_multi.CASES["robot4"]
    assert robot["synchronized"] and list(robot["videos"]) == ["right", "front", "left", "back"]
    for (name, spec), a in zip(robot["videos"].items(), (0.0, 90.0, 180.0, 270.0)):
        assert spec == dict(source="gltf/threejs_RobotExpressive.glb", clip="Walking", frames=48, fps=30.0,
                            size=(320, 240), elev=15.0, path="pan", azim=(a, a))
    horse = bench_multi.CASES["horse2"]
    assert not horse["synchronized"] and horse["videos"]["right"] == bench_multi.SYNTH["horse"]  # bench_fit's horse
    assert horse["videos"]["right"]["azim"] == (-60.0, 60.0) and horse["videos"]["left"]["azim"] == (120.0, 240.0)
    assert {k: v for k, v in horse["videos"]["left"].items() if k != "azim"} == {
        k: v for k, v in horse["videos"]["right"].items() if k != "azim"}
    mirror = bench_multi.CASES["horse-mirror"]
    assert mirror["videos"] == {"right": bench_multi.SYNTH["horse"], "mirrored": {"mirror": "right"}}


def test_a_case_renders_its_videos_once_into_their_folders(renders, tmp_path):
    data, calls = renders
    videos = bench_multi.prepare_videos("robot4", tmp_path)
    root = tmp_path / "sequences" / "robot4"
    assert videos == {name: root / name for name in ("right", "front", "left", "back")}
    assert all((seq / "images" / "000002.png").is_file() and (seq / "masks").is_dir() for seq in videos.values())
    assert [(out.name, spec["azim"], spec["path"]) for out, spec in calls] == [
        ("right", (0.0, 0.0), "pan"), ("front", (90.0, 90.0), "pan"), ("left", (180.0, 180.0), "pan"),
        ("back", (270.0, 270.0), "pan")]
    assert all(spec["source"] == data / "gltf" / "threejs_RobotExpressive.glb" for _, spec in calls)
    assert bench_multi.prepare_videos("robot4", tmp_path) == videos and len(calls) == 4  # rendered once


def test_horse_mirror_makes_the_mirror_of_its_orbit(renders, tmp_path):
    _, calls = renders
    videos = bench_multi.prepare_videos("horse-mirror", tmp_path)
    assert list(videos) == ["right", "mirrored"]
    assert [(out.name, spec["azim"]) for out, spec in calls] == [("right", (-60.0, 60.0))]  # one render only
    for sub in ("images", "masks"):
        for p in sorted((videos["right"] / sub).iterdir()):
            flipped = np.array(Image.open(videos["mirrored"] / sub / p.name))
            assert np.array_equal(flipped, np.array(Image.open(p))[:, ::-1])
    assert (videos["mirrored"] / "keypoints.json").is_file() and not (videos["mirrored"] / "ground_truth").exists()


def test_a_missing_model_skips_the_case_with_a_message(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(bench_multi, "DATA", tmp_path / "nothing")
    assert bench_multi.prepare_videos("horse2", tmp_path) is None
    err = capsys.readouterr().err
    assert "bench_multi: skip horse2:" in err and "quaternius_Horse.glb not found (set S3O_SHARED_DATA)" in err
    assert not (tmp_path / "sequences").exists()  # nothing rendered
    with pytest.raises(SystemExit, match="unknown case horse3"):
        bench_multi.prepare_videos("horse3", tmp_path)


def test_videos_rendered_earlier_need_no_model(renders, tmp_path, monkeypatch):
    videos = bench_multi.prepare_videos("horse2", tmp_path)
    monkeypatch.setattr(bench_multi, "DATA", tmp_path / "nothing")
    assert bench_multi.prepare_videos("horse2", tmp_path) == videos


def _metrics(iou, pck, fscore=None, limbs=None):
    """A one-video metrics dict as the fit returns it (the ground truth's figures only where ``fscore`` is given)."""
    m = {"mask_iou": {"mean": iou, "per_frame": [iou]}, "pck_t": {"pck": pck}}
    if fscore is not None:
        m.update(shape_3d={"fscore": fscore, "chamfer": 0.02},
                 views={"framewise": {"mean": fscore + 0.2}, "sequence": {"mean": fscore + 0.1}},
                 surface={"normal_consistency": 0.8, "roughness": {"pred": 0.1, "truth": 0.05}},
                 skeleton={"limbs_distinct": {"covered": limbs, "total": 11, "limbs": []}})
    return m


def test_a_row_takes_each_videos_figures_and_their_means():
    joint = {"videos": {"right": _metrics(0.9, 80.0, 0.5, 4), "mirrored": _metrics(0.8, 70.0)},
             "mean": {"ignored": True},
             "registration": {"right": {"yaw_deg": 0.0, "margin": 0.3, "turn_rate": 1.5, "per_frame": [0.0]},
                              "mirrored": {"yaw_deg": 180.0, "margin": 0.2, "turn_rate": -1.5, "flipped": True}}}
    row = bench_multi.multi_row(joint, 123.44, case="horse-mirror", seed=0)
    assert row["case"] == "horse-mirror" and row["videos"] == ["right", "mirrored"] and row["wall_seconds"] == 123.4
    right, mirrored = row["joint"]["right"], row["joint"]["mirrored"]
    assert right["iou"] == 0.9 and right["pck_t"] == 80.0 and right["fscore"] == 0.5
    assert right["novel_iou_framewise"] == pytest.approx(0.7) and right["novel_iou_sequence"] == pytest.approx(0.6)
    assert (right["normal_consistency"], right["roughness"], right["roughness_truth"]) == (0.8, 0.1, 0.05)
    assert (right["limbs_distinct"], right["limbs_total"]) == (4, 11)
    assert right["registration"] == {"yaw_deg": 0.0, "margin": 0.3, "turn_rate": 1.5}  # the per-frame list left out
    assert mirrored["registration"]["yaw_deg"] == 180.0 and mirrored["registration"]["flipped"] is True
    assert mirrored["fscore"] is None and mirrored["limbs_distinct"] is None  # no ground truth
    mean = row["mean"]
    assert mean["iou"] == pytest.approx(0.85) and mean["pck_t"] == pytest.approx(75.0)
    assert mean["fscore"] == 0.5 and mean["limbs_distinct"] == 4  # over the videos that have it
    assert "alone" not in row

    alone = {"right": (_metrics(0.92, 84.0, 0.6, 5), 60.04), "mirrored": (_metrics(0.7, 50.0), 50.0)}
    row = bench_multi.multi_row(joint, 123.44, alone, case="horse-mirror", seed=0)
    assert row["alone"]["right"]["pck_t"] == 84.0 and row["alone"]["right"]["wall_seconds"] == 60.0
    assert row["alone_mean"]["pck_t"] == pytest.approx(67.0) and row["alone_mean"]["fscore"] == 0.6
    assert row["alone_wall_seconds"] == 110.0 and "registration" not in row["alone"]["right"]
    json.dumps(row)  # a row is JSON as it stands


def test_main_fits_together_then_alone_and_records_the_row(renders, tmp_path, monkeypatch):
    """The whole command with the fit and the settings faked: the joint fit gets every video with the case's
    synchronization, each video alone gets motion.synchronized=false, and the row lands in multi-<device>.json."""
    fits = []

    def fake_config(preset, overrides, seed):
        sync = [o.split("=")[1] for o in overrides if o.startswith("motion.synchronized=")][-1] == "true"
        return SimpleNamespace(motion=SimpleNamespace(synchronized=sync))

    def fake_fit(seq, run, cfg, device):
        fits.append((seq, Path(run).name, cfg.motion.synchronized))
        if isinstance(seq, list):
            return {"videos": {Path(s).name: _metrics(0.9, 80.0, 0.5, 4) for s in seq},
                    "registration": {Path(s).name: {"yaw_deg": 90.0 * k} for k, s in enumerate(seq)}}
        return _metrics(0.8, 70.0, 0.4, 3)

    monkeypatch.setattr(bench_multi, "make_config", fake_config)
    monkeypatch.setattr(bench_multi, "fit", fake_fit)
    monkeypatch.setattr(bench_multi, "REPO", tmp_path)
    monkeypatch.setattr(bench_multi, "git_commit", lambda: "a" * 40)
    out = tmp_path / "out"
    argv = ["--cases", "robot4", "--out-dir", str(out), "--set", "coarse.steps=5"]
    monkeypatch.setattr(sys, "argv", ["scripts/bench_multi.py"] + argv)
    assert bench_multi.main(argv) == 0
    seqs = [out / "sequences" / "robot4" / v for v in ("right", "front", "left", "back")]
    assert fits == [(seqs, "robot4-0", True)] + [(s, f"robot4-{s.name}-alone-0", False) for s in seqs]
    doc = json.loads((tmp_path / "benchmarks" / "multi-cpu.json").read_text())
    (row,) = doc["results"]
    assert doc["command"] == "python scripts/bench_multi.py --cases robot4 --out-dir OUT_DIR --set coarse.steps=5"
    assert row["synchronized"] is True and row["overrides"] == ["coarse.steps=5"] and row["git_commit"] == "a" * 40
    assert row["joint"]["left"]["registration"] == {"yaw_deg": 180.0} and row["mean"]["pck_t"] == 80.0
    assert list(row["alone"]) == ["right", "front", "left", "back"] and row["alone_mean"]["pck_t"] == 70.0
    fits.clear()
    bench_multi.main(["--cases", "robot4", "--out-dir", str(out), "--no-alone", "--set", "coarse.steps=5"])
    assert [f[1] for f in fits] == ["robot4-0"]
    (row,) = json.loads((tmp_path / "benchmarks" / "multi-cpu.json").read_text())["results"]  # the rerun replaced it
    assert "alone" not in row

    # --rescore: no fit; the runs scored again, the row's commit and wall time kept
    fits.clear()
    scored = []
    monkeypatch.setattr(bench_multi, "evaluate_run", lambda run, seq, progress: scored.append(Path(run).name)
                        or _metrics(0.95, 90.0, 0.6, 4))
    (out / "runs" / "robot4-0" / "metrics.json").parent.mkdir(parents=True, exist_ok=True)
    top = {"videos": {v: {"mask_iou": {"mean": 0.9}} for v in ("right", "front", "left", "back")},
           "registration": {"left": {"yaw_deg": 90.0}}}
    (out / "runs" / "robot4-0" / "metrics.json").write_text(json.dumps(top))
    monkeypatch.setattr(bench_multi, "git_commit", lambda: "b" * 40)
    assert bench_multi.main(["--cases", "robot4", "--out-dir", str(out), "--rescore", "--set", "coarse.steps=5"]) == 0
    assert fits == [] and scored == ["right", "front", "left", "back"]
    (new,) = json.loads((tmp_path / "benchmarks" / "multi-cpu.json").read_text())["results"]
    assert (new["git_commit"], new["rescored_commit"], new["wall_seconds"]) == ("a" * 40, "b" * 40, row["wall_seconds"])
    assert new["mean"]["pck_t"] == 90.0 and new["joint"]["left"]["registration"] == {"yaw_deg": 90.0}
    assert bench_multi.main(["--cases", "robot4", "--out-dir", str(out), "--rescore", "--seeds", "3"]) == 0  # none
    top["videos"]["left"]["mask_iou"]["mean"] = 0.5  # runs of another fit than the rows': nothing rescored
    (out / "runs" / "robot4-0" / "metrics.json").write_text(json.dumps(top))
    scored.clear()
    assert bench_multi.main(["--cases", "robot4", "--out-dir", str(out), "--rescore", "--set", "coarse.steps=5"]) == 0
    assert scored == []


def test_registration_error_reads_a_wrong_turn_from_the_truth(tmp_path):
    """A video whose fit holds the shared body turned by 180 degrees about the vertical reads ~180; one registered as
    the truth is, 0 (each video's cameras its own, the second moving)."""
    import trimesh
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    X = rng.normal(size=(60, 3)) * [1.0, 0.4, 0.2]  # an elongated body: its turn is well defined
    faces = np.array([[0, 1, 2]])
    run = tmp_path / "run"
    run.mkdir()
    trimesh.Trimesh(X, faces, process=False).export(run / "canonical.ply")
    T = 4
    turn = Rotation.from_euler("y", 180, degrees=True).as_matrix()
    videos = {}
    for name, az, wrong in (("a", 0.0, False), ("b", 90.0, False), ("c", 200.0, True)):
        w2c = np.tile(np.eye(4), (T, 1, 1))
        for t in range(T):
            w2c[t, :3, :3] = Rotation.from_euler("y", az + 5 * t, degrees=True).as_matrix()
            w2c[t, :3, 3] = [0.1 * t, 0.0, 6.0]
        gt_verts = X @ w2c[:, :3, :3].transpose(0, 2, 1) + w2c[:, None, :3, 3]
        fit_verts = (X @ turn.T if wrong else X) @ w2c[:, :3, :3].transpose(0, 2, 1) + w2c[:, None, :3, 3]
        seq = videos[name] = tmp_path / "seqs" / name
        (seq / "ground_truth").mkdir(parents=True)
        np.savez(seq / "ground_truth" / "ground_truth.npz", verts=gt_verts, faces=faces, cam_from_world=w2c)
        own = run / "videos" / name
        own.mkdir(parents=True)
        np.savez(own / "motion.npz", verts_cam=2.0 * fit_verts)  # scale and depth do not matter
    videos["m"] = tmp_path / "seqs" / "m"  # a video without ground truth (a mirrored copy): left out
    err = bench_multi.registration_errors(run, videos, frames=3)
    assert err["a"] == 0.0 and err["b"] == pytest.approx(0.0, abs=0.1) and err["c"] == pytest.approx(180.0, abs=0.1)
    assert set(err) == {"a", "b", "c"}
