"""s3o-batch on a local Ray with 2 CPUs: three tiny sequences at the smoke preset (one broken), a re-run that
does no work, a killed worker that is retried, bad input refused before Ray starts, and the same command on a
cluster started with ``ray start --head`` (stopped with Ctrl-C, then resumed)."""

from __future__ import annotations

import csv
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from s3o_warp import batch
from s3o_warp.errors import InputError

ray = pytest.importorskip("ray", reason="ray is not installed: pip install -e '.[test]' (or '.[batch]')")

SMOKE = ["--preset", "smoke", "--set", "data.crop_size=48", "--set", "output.render_video=false"]
"""Settings of every test fit: the smoke preset at 48 px crops, no videos (a fit is seconds)."""


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray with 2 CPUs for the module's tests (s3o-batch uses the Ray this process already runs)."""
    ray.init(address="local", num_cpus=2, log_to_driver=False, logging_level=logging.ERROR, include_dashboard=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def sequences(tmp_path_factory):
    """A folder of three 6-frame 64x48 clips of the built-in quadruped; ``s1`` lacks one mask (bad input)."""
    from s3o_warp.synth import make_sequence

    root = tmp_path_factory.mktemp("batch") / "seqs"
    for i in range(3):
        make_sequence(root / f"s{i}", frames=6, size=(64, 48), azim=(-15.0, 15.0), seed=i, progress=False)
    sorted((root / "s1" / "masks").iterdir())[0].unlink()
    return root


def read_csv(path: Path) -> dict[str, dict]:
    with open(path, newline="") as f:
        return {r["name"]: r for r in csv.DictReader(f)}


def run_files(run: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(run)): (p.stat().st_mtime_ns, p.stat().st_size) for p in run.rglob("*") if p.is_file()}


def test_batch_reports_the_broken_fit_and_a_rerun_does_no_work(local_ray, sequences, tmp_path, monkeypatch):
    runs = tmp_path / "runs"
    rc = batch.main([str(sequences), "--out", str(runs), *SMOKE])
    assert rc == 1  # one fit failed
    rows = read_csv(runs / "summary.csv")
    assert list(rows) == ["s0", "s1", "s2"]
    doc = json.loads((runs / "summary.json").read_text())
    assert doc["counts"] == {"finished": 2, "failed": 1}
    for name in ("s0", "s2"):
        r = rows[name]
        metrics = json.loads((runs / name / "metrics.json").read_text())
        assert r["status"] == "finished" and r["error"] == "" and r["attempts"] == "1"
        assert int(r["frames"]) == metrics["frames"] == 6
        assert int(r["bones"]) == metrics["bones"]["count"] > 1
        assert float(r["mask_iou"]) == pytest.approx(metrics["mask_iou"]["mean"], rel=1e-5) and float(r["mask_iou"]) > 0.3
        assert float(r["pck_t"]) == pytest.approx(metrics["pck_t"]["pck"], rel=1e-5)  # keypoints.json of the clip
        assert float(r["chamfer"]) == pytest.approx(metrics["shape_3d"]["chamfer"], rel=1e-5)  # its ground truth
        assert float(r["joint_distance"]) == pytest.approx(metrics["skeleton"]["distance"], rel=1e-5)
        assert r["device"].startswith("cpu, 1 torch threads") and float(r["wall_s"]) > 0
    bad = rows["s1"]
    assert bad["status"] == "failed" and "masks" in bad["error"] and "\n" not in bad["error"]
    assert not (runs / "s1" / "metrics.json").exists() and not (runs / "s1" / "config.toml").exists()

    # the same command again: the finished runs are left as they are and their rows kept; the broken one is
    # tried again (its input may have been fixed) and fails the same way
    before = {n: run_files(runs / n) for n in ("s0", "s2")}
    rc = batch.main([str(sequences), "--out", str(runs), *SMOKE])
    assert rc == 1
    again = json.loads((runs / "summary.json").read_text())["rows"]
    assert [r["status"] for r in again] == ["finished", "failed", "finished"]
    assert again[0]["reused"] and again[2]["reused"] and "reused" not in again[1]
    assert {k: v for k, v in again[0].items() if k != "reused"} == doc["rows"][0]
    assert {n: run_files(runs / n) for n in ("s0", "s2")} == before
    assert again[1]["error"] == doc["rows"][1]["error"]

    # only finished sequences (a manifest of two rows): no Ray at all
    manifest = tmp_path / "done.csv"
    manifest.write_text(f"path\n{sequences / 's0'}\n{sequences / 's2'}\n")

    def no_ray(address):
        raise AssertionError("Ray was started for a batch with nothing to fit")

    monkeypatch.setattr(batch, "connect", no_ray)
    assert batch.main([str(manifest), "--out", str(runs), *SMOKE]) == 0
    assert {n: run_files(runs / n) for n in ("s0", "s2")} == before
    assert list(read_csv(runs / "summary.csv")) == ["s0", "s2"]


def test_a_killed_worker_is_retried_from_its_checkpoint(local_ray, sequences, tmp_path):
    runs = tmp_path / "runs"
    manifest = tmp_path / "one.json"  # a JSON manifest, with the row's own settings: long enough to be killed
    manifest.write_text(json.dumps([{"path": str(sequences / "s0"), "run": "killed", "motion.steps": 60,
                                     "output.checkpoint_every": 5}]))
    out: dict = {}
    t = threading.Thread(target=lambda: out.update(rc=batch.main([str(manifest), "--out", str(runs), *SMOKE])))
    t.start()
    run, killed = runs / "killed", None
    deadline = time.monotonic() + 300
    while t.is_alive() and time.monotonic() < deadline and killed is None:
        time.sleep(0.2)
        joint = sorted((run / "checkpoints").glob("step-2-joint-*.pt")) if (run / "checkpoints").is_dir() else []
        if any(not p.name.endswith("000000.pt") for p in joint):  # some joint steps are checkpointed
            starts = [json.loads(x) for x in (run / batch.LOG_NAME).read_text().splitlines() if '"start"' in x]
            killed = starts[-1]["pid"]
            os.kill(killed, signal.SIGKILL)
    t.join(timeout=300)
    assert killed is not None, "the fit ended before a joint checkpoint was seen"
    assert out["rc"] == 0
    row = json.loads((runs / "summary.json").read_text())["rows"][0]
    assert row["status"] == "finished" and row["attempts"] == 2
    starts = [json.loads(x) for x in (run / batch.LOG_NAME).read_text().splitlines() if '"start"' in x]
    assert starts[0]["pid"] == killed and starts[1]["pid"] != killed
    assert "resuming from" in (run / batch.FIT_LOG).read_text()
    steps = [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines()]
    assert max(r["step"] for r in steps if r["phase"] == "joint") == 60


def _manifest(tmp_path, text: str, name: str = "m.csv") -> str:
    p = tmp_path / name
    p.write_text(text)
    return str(p)


@pytest.mark.parametrize("case, args, words", [
    ("no inputs", lambda s, t: [str(t / "nope")], ["nope", "no such file"]),
    ("unknown column", lambda s, t: [_manifest(t, f"path,color\n{s / 's0'},red\n")], ["row 2", "'color'"]),
    ("bad setting", lambda s, t: [_manifest(t, f"path,motion.steps\n{s / 's0'},10\n{s / 's2'},many\n")],
     ["row 3", "motion.steps"]),
    ("missing path", lambda s, t: [_manifest(t, f"path\n{s / 's0'}\n{s / 'gone'}\n")], ["row 3", "gone"]),
    ("same run twice", lambda s, t: [_manifest(t, json.dumps([{"path": str(s / "s0")}, {"path": str(s / "s0")}]),
                                               "m.json")], ["row 2", "'s0'"]),
    ("masks per video", lambda s, t: [_manifest(t, f"path,masks\n{s / 's0'};{s / 's2'},{s / 's0' / 'masks'}\n")],
     ["row 2", "1 mask folder(s) for 2 video(s)"]),
    ("empty path entry", lambda s, t: [_manifest(t, f"path\n{s / 's0'};\n")], ["row 2", "empty entry"]),
    ("synchronized alone", lambda s, t: [_manifest(t, f"path,motion.synchronized\n{s / 's0'},true\n")],
     ["row 2", "needs several videos"]),
    ("names without DAVIS", lambda s, t: [str(s), "--names", "cows"], ["--names", "JPEGImages"]),
    ("bad --set", lambda s, t: [str(s), "--set", "motion.nope=1"], ["motion.nope"]),
    ("bad cpus", lambda s, t: [str(s), "--cpus-per-fit", "0"], ["--cpus-per-fit"]),
    ("no sequences", lambda s, t: [str(t)], ["no sequence folders"]),
])
def test_bad_input_is_one_line_before_ray(sequences, tmp_path, capsys, monkeypatch, case, args, words):
    def no_ray(address):
        raise AssertionError("Ray was started on bad input")

    monkeypatch.setattr(batch, "connect", no_ray)
    runs = tmp_path / "runs"
    assert batch.main([*args(sequences, tmp_path), "--out", str(runs), *SMOKE]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("s3o-batch: error: ") and "\n" not in err, err
    for w in words:
        assert w in err, (w, err)
    assert not runs.exists()


def test_inputs_of_every_kind(tmp_path):
    for seq in ("a", "b"):
        (tmp_path / "clips" / seq / "images").mkdir(parents=True)
    (tmp_path / "clips" / "notes").mkdir()  # no images/: not a sequence
    assert [(i.run, i.path) for i in batch.collect_items(str(tmp_path / "clips"))] == [
        ("a", str(tmp_path / "clips" / "a")), ("b", str(tmp_path / "clips" / "b"))]
    assert [i.run for i in batch.collect_items(str(tmp_path / "clips" / "b"))] == ["b"]  # one sequence folder

    davis = tmp_path / "DAVIS"
    for seq in ("cows", "dog"):
        (davis / "JPEGImages" / "480p" / seq).mkdir(parents=True)
    items = batch.collect_items(str(davis), ["dog"])
    assert [(i.run, i.path, i.name) for i in items] == [("dog", str(davis), "dog")]
    with pytest.raises(InputError, match="--names horse: no such sequence .* cows, dog"):
        batch.collect_items(str(davis), ["horse"])
    with pytest.raises(InputError, match="pass --names"):
        batch.collect_items(str(davis))

    (tmp_path / "lists").mkdir()
    manifest = tmp_path / "lists" / "m.json"  # paths relative to the manifest's folder; a row's own settings
    manifest.write_text(json.dumps([{"path": "../clips/a", "masks": "../clips/a/images", "seed": 3},
                                    {"path": str(davis), "name": "cows", "run": "cows-2", "motion.steps": 20}]))
    a, cows = batch.collect_items(str(manifest))
    assert (a.run, Path(a.path).resolve(), Path(a.masks).resolve(), a.settings) == (
        "a", tmp_path / "clips" / "a", tmp_path / "clips" / "a" / "images", ("seed=3",))
    assert (cows.run, cows.name, cows.settings) == ("cows-2", "cows", ("motion.steps=20",))
    cfg_a, cfg_cows = batch.check_items([a, cows], "smoke", None, ["motion.steps=30"], seed=7)
    assert (cfg_a.seed, cfg_a.motion.steps) == (3, 30) and (cfg_cows.seed, cfg_cows.motion.steps) == (7, 20)


def test_manifest_row_of_several_videos(tmp_path, monkeypatch):
    for seq in ("left", "right"):
        (tmp_path / "clips" / seq / "masks").mkdir(parents=True)
    csv_m = tmp_path / "m.csv"  # CSV: the videos of one object in one cell, ';' between them
    csv_m.write_text("path,masks,motion.synchronized\nclips/left; clips/right,clips/left/masks;clips/right/masks,true\n")
    json_m = tmp_path / "m.json"
    json_m.write_text(json.dumps([{"path": ["clips/left", "clips/right"], "run": "pair"}, {"path": "clips/left"}]))
    (row,) = batch.collect_items(str(csv_m))
    assert row.run == "left+right" and row.settings == ("motion.synchronized=true",)
    assert [Path(p).resolve() for p in row.path] == [tmp_path / "clips" / "left", tmp_path / "clips" / "right"]
    assert [Path(p).resolve() for p in row.masks] == [tmp_path / "clips" / v / "masks" for v in ("left", "right")]
    pair, single = batch.collect_items(str(json_m))
    assert (pair.run, len(pair.path), pair.masks) == ("pair", 2, None)
    assert isinstance(single.path, str) and single.run == "left"
    (cfg,) = batch.check_items([row], "smoke", None, [], seed=0)
    assert cfg.motion.synchronized

    seen = {}

    def fake_fit(seq, run, cfg, device, resume=False, masks=None, name=None):
        seen.update(seq=seq, masks=masks)
        one = {"frames": 4, "mask_iou": {"mean": 0.9}, "bones": {"count": 5}}
        two = {"frames": 6, "mask_iou": {"mean": 0.7}, "bones": {"count": 5}}
        return {"videos": {"left": one, "right": two}, "mean": {"mask_iou": {"mean": 0.8}, "bones": {"count": 5.0}},
                "seconds": 12.5}

    monkeypatch.setattr(batch, "fit", fake_fit)
    monkeypatch.setattr(batch.torch, "set_num_threads", lambda n: None)  # a worker's; this process keeps its own
    out = batch.fit_one(row, cfg, str(tmp_path / "runs"), "b1", 1)  # the fit is given the list of videos
    assert seen["seq"] == list(row.path) and seen["masks"] == list(row.masks)
    assert (out["status"], out["frames"], out["mask_iou"], out["bones"], out["fit_s"]) == ("finished", 10, 0.8, 5.0,
                                                                                           12.5)


def test_resources_per_fit():
    cpu_node, gpu_node = {"CPU": 2, "GPU": 0}, {"CPU": 16, "GPU": 4}
    assert batch.resources([cpu_node], None, None) == (1, 0)  # a fit per core
    assert batch.resources([cpu_node, gpu_node], None, None) == (4, 1)  # a GPU per fit, the node's CPUs shared
    assert batch.resources([{"CPU": 6, "GPU": 2}, gpu_node], None, None) == (3, 1)  # the smallest share decides
    assert batch.resources([gpu_node], None, 2) == (8, 2)
    assert batch.resources([cpu_node], 2, 0) == (2, 0)
    with pytest.raises(InputError, match="--gpus-per-fit 1: no Ray node"):
        batch.resources([cpu_node], None, 1)
    with pytest.raises(InputError, match="--cpus-per-fit 4: .*most: 2"):
        batch.resources([cpu_node], 4, None)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_same_command_on_a_cluster_stops_and_resumes(sequences, tmp_path):
    """``ray start --head`` on 127.0.0.1, then ``s3o-batch --address``: Ctrl-C checkpoints the running fit, the same
    command resumes it."""
    exe = Path(sys.executable).parent
    ray_cli, cli = exe / "ray", exe / "s3o-batch"
    if not ray_cli.exists() or not cli.exists():
        pytest.skip(f"the ray and s3o-batch commands are not installed beside {sys.executable}")
    port = _free_port()
    # a throwaway cluster on 127.0.0.1: without Ray's token authentication, which an explicit --address only uses
    # with RAY_AUTH_MODE=token and the cluster's token (README)
    env = {**{k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}, "RAY_AUTH_MODE": "disabled"}
    temp = Path("/tmp") / f"s3o-ray-{os.getpid()}"  # the cluster's sockets: short paths (tmp_path is too long)
    # --block keeps `ray start` in the foreground: stopping it stops this cluster's processes and no other Ray here
    head = subprocess.Popen([str(ray_cli), "start", "--head", "--block", f"--port={port}", "--node-ip-address=127.0.0.1",
                             "--num-cpus=2", "--include-dashboard=false", "--disable-usage-stats", f"--temp-dir={temp}"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 120
    while head.poll() is None and time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                break
        time.sleep(0.5)
    else:
        head.kill()
        why = head.communicate()[1].strip().splitlines()[-1:] if head.poll() is not None else "no answer in 120 s"
        shutil.rmtree(temp, ignore_errors=True)
        pytest.skip(f"ray start --head could not start a cluster here: {why}")
    try:
        runs = tmp_path / "runs"
        manifest = _manifest(tmp_path, json.dumps([{"path": str(sequences / "s2"), "motion.steps": 100}]), "m.json")
        cmd = [str(cli), manifest, "--out", str(runs), "--address", f"127.0.0.1:{port}", *SMOKE]
        # SIGINT as from a terminal, even where this suite runs with it ignored (nohup ... &: the child inherits it)
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        deadline = time.monotonic() + 300
        ck = runs / "s2" / "checkpoints"
        while proc.poll() is None and time.monotonic() < deadline:
            if ck.is_dir() and any(ck.glob("step-2-joint-*.pt")):  # in the joint phase
                proc.send_signal(signal.SIGINT)
                break
            time.sleep(0.2)
        out = proc.communicate(timeout=300)[0]
        assert proc.returncode == 130, out
        row = json.loads((runs / "summary.json").read_text())["rows"][0]
        assert row["status"] == "interrupted" and "checkpoint" in row["error"], row
        assert Path(row["error"].rsplit("checkpoint ", 1)[1]).is_file()
        assert json.loads((runs / "summary.json").read_text())["address"] == f"127.0.0.1:{port}"

        done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
        assert done.returncode == 0, done.stdout + done.stderr
        row = json.loads((runs / "summary.json").read_text())["rows"][0]
        assert row["status"] == "finished" and int(row["frames"]) == 6
        assert "resuming from" in (runs / "s2" / batch.FIT_LOG).read_text()
    finally:
        head.send_signal(signal.SIGTERM)
        try:
            head.wait(timeout=60)
        except subprocess.TimeoutExpired:
            head.kill()
        shutil.rmtree(temp, ignore_errors=True)
