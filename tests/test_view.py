"""s3o-view: the run directory read into world-frame arrays (against motion.npz), the page served on a free port,
drawn in headless Chromium (skipped without Debian's chromium), the slider moving the mesh and bones, looking through
a fitted camera, a running fit's checkpoint shown and replaced by a newer one, a fit of several videos shown one at a
time (finished and running; the "video" selector, ``--video``), and bad input as one line, exit 2."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from conftest import smoke_config
from s3o_warp.errors import InputError
from s3o_warp.fit import fit
from s3o_warp.view import cli
from s3o_warp.view.glb import mesh_glb
from s3o_warp.view.run import checkpoints, figures, load_view, video_spans

REPO = Path(__file__).resolve().parents[1]
CHROMIUM = "/usr/bin/chromium"
MAGENTA, GREEN = (255, 0, 255), (0, 255, 0)


@pytest.fixture(scope="module")
def run_dir(tiny_sequence, tmp_path_factory) -> Path:
    """A finished smoke fit of the 8-frame quadruped (about 10 s)."""
    run = tmp_path_factory.mktemp("view") / "quad"
    fit(tiny_sequence, run, smoke_config(), torch.device("cpu"))
    return run


B_FRAMES = [6, 5, 4, 3, 2, 1]
"""Video b of :func:`videos_run`: these frames of the fit, in this order (a motion of its own, 6 frames)."""
PER_FRAME = ("verts_cam", "joints_cam", "root", "K", "bone_motion", "frame_names")
"""What ``motion.npz`` holds frame by frame."""


@pytest.fixture(scope="module")
def videos_run(run_dir, tmp_path_factory) -> Path:
    """A finished fit of two videos as the fit writes one: the smoke fit as video a, its frames :data:`B_FRAMES` as
    video b (``videos/<name>/`` a one-video run directory each), the shared mesh and skeleton, ``videos.json``."""
    run = tmp_path_factory.mktemp("view-videos") / "two"
    run.mkdir()
    for name in ("canonical.ply", "skeleton.json", "config.toml"):
        shutil.copy2(run_dir / name, run)
    metrics = {}
    for name in ("a", "b"):
        sub = run / "videos" / name
        shutil.copytree(run_dir, sub, ignore=shutil.ignore_patterns("checkpoints", "cache", "config.toml", "log.jsonl"))
        metrics[name] = json.loads((sub / "metrics.json").read_text())
    z = dict(np.load(run_dir / "motion.npz"))
    np.savez(run / "videos" / "b" / "motion.npz", **{k: a[B_FRAMES] if k in PER_FRAME else a for k, a in z.items()})
    metrics["b"]["frames"] = len(B_FRAMES)
    (run / "videos" / "b" / "metrics.json").write_text(json.dumps(metrics["b"]))
    (run / "metrics.json").write_text(json.dumps({"videos": metrics, "mean": metrics["a"], "registration": {}}))
    (run / "videos.json").write_text(json.dumps({"videos": ["a", "b"]}))
    return run


def _world(run: Path, t: int) -> np.ndarray:
    """Frame t's posed vertices from motion.npz, taken into the world frame through that frame's camera."""
    z = np.load(run / "motion.npz")
    G = np.asarray(json.loads((run / "skeleton.json").read_text())["world_from_object"])
    c2w = G @ np.linalg.inv(z["root"][t])
    return z["verts_cam"][t] @ c2w[:3, :3].T + c2w[:3, 3]


# ------------------------------------------------------------------------------------------ the run read
def test_view_of_a_finished_run_is_motion_npz_in_the_world_frame(run_dir):
    v = load_view(run_dir)
    z = np.load(run_dir / "motion.npz")
    T, N = z["verts_cam"].shape[:2]
    assert v.label == "finished fit" and v.verts.shape == (T, N, 3) and v.num_frames == T
    for t in (0, T - 1):
        np.testing.assert_allclose(v.verts[t], _world(run_dir, t), atol=1e-5)
        cam = np.linalg.inv(v.cam_to_world[t])  # the world back into frame t's camera: motion.npz's own points
        np.testing.assert_allclose(v.verts[t] @ cam[:3, :3].T + cam[:3, 3], z["verts_cam"][t], atol=1e-5)
    assert v.joints.shape[1] == z["joints_cam"].shape[1] > 0
    assert len(v.bone_links) == 2 * v.joints.shape[1]  # a segment from each joint to each of its two bones
    assert v.bone_segments(3).shape == (len(v.bone_links), 2, 3)
    assert v.image_size == tuple(z["image_size"]) and v.fps == float(z["fps"])
    assert v.sequence is not None  # metrics.json names it: the cameras get their pictures
    names = dict(figures(v.metrics))
    assert {"mask IoU", "PCK-T", "bones", "F-score @2%"} <= set(names)
    assert "[motion]" in v.config_text


def test_glb_holds_the_mesh_and_its_colours():
    import pygltflib

    rng = np.random.default_rng(0)
    verts = rng.normal(size=(5, 3)).astype(np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3], [1, 3, 4]])
    colors = rng.uniform(size=(5, 3)).astype(np.float32)
    g = pygltflib.GLTF2.load_from_bytes(mesh_glb(verts, faces, colors))
    blob = g.binary_blob()

    def read(i, dtype):  # an accessor's data, three numbers a row
        bv = g.bufferViews[g.accessors[i].bufferView]
        return np.frombuffer(blob[bv.byteOffset:bv.byteOffset + bv.byteLength], dtype).reshape(-1, 3)

    prim = g.meshes[0].primitives[0]
    np.testing.assert_array_equal(read(prim.attributes.POSITION, "<f4"), verts)
    np.testing.assert_array_equal(read(prim.attributes.COLOR_0, "<f4"), colors)
    np.testing.assert_array_equal(read(prim.indices, "<u4"), faces)
    assert g.accessors[prim.attributes.POSITION].min == verts.min(0).tolist()


# ---------------------------------------------------------------------------------------------- the page
def test_the_slider_moves_the_mesh_and_bones_as_motion_npz_does(run_dir):
    pytest.importorskip("viser")
    from s3o_warp.view.server import ViewServer

    srv = ViewServer(run_dir, port=0, poll_s=0)
    try:
        v = srv.view
        assert srv.frame == 0
        np.testing.assert_allclose(srv.plain.vertices, _world(run_dir, 0), atol=1e-5)
        bones0 = np.array(srv.bones.points)
        srv.slider.value = 5  # what the page's slider sends
        assert srv.frame == 5
        moved = np.asarray(srv.plain.vertices) - _world(run_dir, 0)
        np.testing.assert_allclose(moved, _world(run_dir, 5) - _world(run_dir, 0), atol=1e-5)
        assert np.abs(moved).max() > 1e-3  # the frames differ
        np.testing.assert_allclose(srv.bones.points, v.bone_segments(5), atol=1e-6)
        assert np.abs(np.asarray(srv.bones.points) - bones0).max() > 1e-4
        assert srv.colour_nodes[5].visible and not srv.colour_nodes[0].visible  # the coloured mesh switched too
        srv.set_playing(True)
        time.sleep(10 / v.fps)
        srv.set_playing(False)
        assert srv.frame != 5  # playing advanced the frames
    finally:
        srv.close()


def test_page_draws_the_mesh_in_headless_chromium_and_looks_through_a_camera(run_dir, monkeypatch):
    pytest.importorskip("viser")
    if not Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} is absent (Debian's chromium: apt-get install chromium): the page is not drawn here")
    from s3o_warp.view import server as server_mod
    from s3o_warp.view.browser import HeadlessPage, colour_pixels

    real_load = server_mod.load_view

    def magenta_load(*a, **k):  # vertex colours that cannot be mistaken for anything else on the page
        view = real_load(*a, **k)
        view.colors[:] = np.asarray(MAGENTA) / 255.0
        return view

    monkeypatch.setattr(server_mod, "load_view", magenta_load)
    srv = server_mod.ViewServer(run_dir, port=0, surface="plain", plain_color=GREEN, poll_s=0)
    try:
        with urllib.request.urlopen(srv.url, timeout=30) as r:  # the page itself is served
            assert r.status == 200 and b"<html" in r.read(2000).lower()
        width = 1100
        with HeadlessPage(srv.url, size=(width, 700), binary=CHROMIUM) as page:
            scene = slice(0, width - 380)  # left of the panel

            def shows(rgb):
                return lambda img: colour_pixels(img[:, scene], rgb) > 200

            img, ok = page.wait_for(shows(GREEN), timeout=120)
            assert ok, f"no mesh-coloured pixels in the page ({colour_pixels(img[:, scene], GREEN)})"
            srv.surface.value = "colours"  # the per-frame coloured meshes
            img, ok = page.wait_for(lambda im: shows(MAGENTA)(im) and not shows(GREEN)(im), timeout=60)
            assert ok, "the vertex-coloured mesh was not drawn in place of the plain one"

            client = next(iter(srv.server.get_clients().values()))
            srv.slider.value = 2
            srv.look_through(client)
            wxyz, pos, fov, _ = srv.camera_pose(2)
            assert _camera_reaches(client, pos, wxyz, fov), "the page's view did not become frame 2's fitted camera"
            assert srv.show_backdrop.value and not srv.show_cameras.value  # the frame behind the mesh, no frusta
            assert srv.backdrop is not None and srv.backdrop.visible
            srv.follow.value = True  # the view follows the fitted camera from frame to frame
            srv.slider.value = 4
            wxyz, pos, fov, _ = srv.camera_pose(4)
            assert _camera_reaches(client, pos, wxyz, fov), "the page's view did not follow to frame 4's camera"
    finally:
        srv.close()


def _camera_reaches(client, pos, wxyz, fov, timeout: float = 30.0) -> bool:
    """Whether the page reports its view at the camera (position, orientation up to sign, vertical fov) within
    ``timeout`` seconds (a report it sent before it took the new view may arrive first)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        cam = client.camera
        q = np.asarray(cam.wxyz)
        if (np.abs(np.asarray(cam.position) - pos).max() < 1e-4 and min(np.abs(q - wxyz).max(), np.abs(q + wxyz).max())
                < 1e-4 and abs(cam.fov - fov) < 1e-4):
            return True
        time.sleep(0.1)
    return False


def test_a_running_fit_shows_its_checkpoint_and_follows_a_newer_one(run_dir, tmp_path):
    pytest.importorskip("viser")
    from s3o_warp.view.server import ViewServer

    running = tmp_path / "running"
    shutil.copytree(run_dir, running)
    for name in ("motion.npz", "metrics.json"):
        (running / name).unlink()
    cks = checkpoints(running)
    assert len(cks) >= 2
    last = cks[-1].rename(tmp_path / cks[-1].name)  # as if the fit had not written its last checkpoint yet
    srv = ViewServer(running, port=0, poll_s=0)
    try:
        assert cks[-2].name in srv.view.label and srv.view.metrics is None
        before = srv.view.verts.copy()
        assert not srv.poll()  # nothing new
        shutil.copy2(last, running / "checkpoints" / last.name)
        assert srv.poll()
        assert last.name in srv.view.label
        np.testing.assert_allclose(srv.view.verts[3], _world(run_dir, 3), atol=1e-4)  # the final state, as saved
        assert before.shape != srv.view.verts.shape or np.abs(srv.view.verts - before).max() > 1e-4
        np.testing.assert_allclose(srv.plain.vertices, srv.view.verts[srv.frame], atol=1e-6)
    finally:
        srv.close()


def test_s3o_view_serves_a_run_on_a_free_port(run_dir):
    pytest.importorskip("viser")
    proc = subprocess.Popen([sys.executable, str(REPO / "scripts" / "view.py"), str(run_dir), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith("s3o-view: http://127.0.0.1:"), (line, proc.stderr.read() if proc.poll() else "")
        url = line.split()[1]
        with urllib.request.urlopen(url, timeout=30) as r:
            assert r.status == 200
    finally:
        proc.terminate()
        proc.wait(timeout=30)


# ----------------------------------------------------------------------------------------- several videos
def test_a_fit_of_several_videos_is_read_one_video_at_a_time(videos_run, run_dir):
    a, b = load_view(videos_run), load_view(videos_run, video="b")
    assert (a.videos, a.video, b.videos, b.video) == (["a", "b"], 0, ["a", "b"], 1)
    assert (a.num_frames, b.num_frames) == (8, len(B_FRAMES)) and a.label == b.label == "finished fit"
    assert b.source == videos_run / "videos" / "b" / "motion.npz"
    for t in (0, len(B_FRAMES) - 1):  # each video's own motion.npz, in the world frame
        np.testing.assert_allclose(b.verts[t], _world(videos_run / "videos" / "b", t), atol=1e-5)
        np.testing.assert_allclose(b.verts[t], a.verts[B_FRAMES[t]], atol=1e-5)
    assert b.frame_names == [a.frame_names[t] for t in B_FRAMES]
    assert dict(figures(b.metrics))["frames"] == str(len(B_FRAMES)) and dict(figures(a.metrics))["frames"] == "8"
    assert "[motion]" in b.config_text and b.sequence is not None
    assert load_view(videos_run, video=1).num_frames == len(B_FRAMES)
    one = load_view(run_dir)
    assert (one.videos, one.video) == ([], 0)


def test_the_video_selector_switches_the_mesh_frames_and_figures(videos_run, run_dir):
    pytest.importorskip("viser")
    from s3o_warp.view.server import ViewServer

    srv = ViewServer(videos_run, port=0, poll_s=0)
    try:
        assert srv.video_select.options == ("a", "b") and srv.video_select.value == "a" and srv.view.video == 0
        a0 = _world(videos_run / "videos" / "a", 0)
        np.testing.assert_allclose(srv.plain.vertices, a0, atol=1e-5)
        srv.slider.value = 7
        srv.video_select.value = "b"  # what the page's selector sends
        assert srv.view.video == 1 and srv.view.num_frames == len(B_FRAMES) and srv.frame == 0
        assert srv.slider.max == len(B_FRAMES) - 1 and "video **b** (2 of 2)" in srv.header.content
        b0 = _world(videos_run / "videos" / "b", 0)
        np.testing.assert_allclose(srv.plain.vertices, b0, atol=1e-5)
        assert np.abs(b0 - a0).max() > 1e-3  # the videos' meshes differ
        assert f"| frames | {len(B_FRAMES)} |" in srv.figures_text.content  # b's own metrics.json
        srv.slider.value = 2
        np.testing.assert_allclose(srv.plain.vertices, _world(videos_run / "videos" / "b", 2), atol=1e-5)
        np.testing.assert_allclose(srv.bones.points, srv.view.bone_segments(2), atol=1e-6)
        srv.video_select.value = "a"
        assert srv.view.video == 0 and srv.view.num_frames == 8
        np.testing.assert_allclose(srv.plain.vertices, a0, atol=1e-5)
        assert not srv.poll()  # nothing new
    finally:
        srv.close()
    srv = ViewServer(videos_run, port=0, poll_s=0, video="b")
    try:
        assert srv.video_select.value == "b" and srv.view.num_frames == len(B_FRAMES)
    finally:
        srv.close()
    srv = ViewServer(run_dir, port=0, poll_s=0)  # one video: no selector
    try:
        assert srv.video_select is None and srv.view.videos == []
    finally:
        srv.close()


def test_a_running_fit_of_several_videos_shows_each_videos_frames(run_dir, videos_run, tmp_path):
    running = tmp_path / "running"
    shutil.copytree(run_dir, running, ignore=shutil.ignore_patterns("cache"))
    for name in ("motion.npz", "metrics.json"):
        (running / name).unlink()
    whole = load_view(running)  # one video: every frame
    assert whole.videos == [] and whole.num_frames == 8
    newest = checkpoints(running)[-1]
    st = torch.load(newest, weights_only=False)
    sd = st["model"]
    sd["video_of"] = torch.tensor([0] * 5 + [1] * 3)  # the same frames as two videos of 5 and 3
    sd["log_focal"] = sd["log_focal"].reshape(1).repeat(2)  # one focal length per video, both the fit's
    st["sequence"] = "left+right"  # the fit's name of its videos
    torch.save(st, newest)
    assert video_spans(sd) == [(0, 5), (5, 8)]
    left, right = load_view(running), load_view(running, video="right")
    assert (left.videos, left.video, right.video) == (["left", "right"], 0, 1)
    assert (left.num_frames, right.num_frames) == (5, 3) and newest.name in right.label and right.metrics is None
    np.testing.assert_allclose(left.verts, whole.verts[:5], atol=1e-5)
    np.testing.assert_allclose(right.verts, whole.verts[5:], atol=1e-5)
    np.testing.assert_allclose(right.K, whole.K[5:], atol=1e-6)
    st["sequence"] = "quad"  # names that do not split into the videos: numbered
    torch.save(st, newest)
    assert load_view(running, video="video 1").videos == ["video 0", "video 1"]
    with pytest.raises(InputError, match="video 0, video 1"):
        load_view(running, video="right")
    pytest.importorskip("viser")
    from s3o_warp.view.server import ViewServer

    srv = ViewServer(running, port=0, poll_s=0, video="video 1")
    try:
        assert srv.video_select.options == ("video 0", "video 1") and srv.view.num_frames == 3
        for name, src in (("left", "a"), ("right", "b")):  # the fit ends: each video's run directory, written now
            shutil.copytree(videos_run / "videos" / src, running / "videos" / name, copy_function=shutil.copy)
        (running / "videos.json").write_text(json.dumps({"videos": ["left", "right"]}))
        assert srv.poll()
        assert srv.video_select.options == ("left", "right") and srv.video_select.value == "right"
        assert srv.view.video == 1 and srv.view.label == "finished fit" and srv.view.num_frames == len(B_FRAMES)
    finally:
        srv.close()


def test_s3o_view_video_picks_the_video_shown_first(videos_run, monkeypatch, capsys):
    pytest.importorskip("viser")

    class Stopped:  # the server starts, prints its line and is stopped at once, as Ctrl-C stops it
        def wait(self):
            raise KeyboardInterrupt

    monkeypatch.setattr(cli, "threading", SimpleNamespace(Event=Stopped))  # cli's own, not the threading module
    assert cli.main([str(videos_run), "--port", "0", "--poll", "0", "--video", "b"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("s3o-view: http://127.0.0.1:") and ", video b of 2 (finished fit)" in out, out


# ---------------------------------------------------------------------------------------------- bad input
def _one_line_exit_2(capsys, argv, *words):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("s3o-view: error:"), err
    for w in words:
        assert w in err, err


def test_bad_input_is_one_line_and_exit_2(run_dir, tmp_path, capsys):
    pytest.importorskip("viser")
    _one_line_exit_2(capsys, [str(tmp_path / "nowhere")], "no such folder")
    (tmp_path / "empty").mkdir()
    _one_line_exit_2(capsys, [str(tmp_path / "empty")], "not a run directory")
    started = tmp_path / "started"  # a fit that has written its settings but nothing else yet
    started.mkdir()
    shutil.copy2(run_dir / "config.toml", started)
    _one_line_exit_2(capsys, [str(started)], "motion.npz", "no checkpoint")
    broken = tmp_path / "broken"
    shutil.copytree(run_dir, broken, ignore=shutil.ignore_patterns("checkpoints"))
    (broken / "motion.npz").write_bytes(b"not an npz")
    _one_line_exit_2(capsys, [str(broken)], "motion.npz")
    with pytest.raises(InputError, match="motion.npz"):
        load_view(broken)
    _one_line_exit_2(capsys, [str(run_dir), "--sequence", str(tmp_path / "frames")], "--sequence")
    _one_line_exit_2(capsys, [str(run_dir), "--video", "a"], "--video a", "one video")


def test_a_video_the_run_lacks_is_one_line_naming_its_videos(videos_run, capsys):
    pytest.importorskip("viser")
    _one_line_exit_2(capsys, [str(videos_run), "--video", "c"], "--video c", "its videos: a, b")


def test_without_viser_one_line_names_the_install(run_dir, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "viser", None)  # import viser -> ImportError
    _one_line_exit_2(capsys, [str(run_dir)], "pip install 's3o-warp[view]'")
