"""One object from several videos: the joined data, the windows, the per-video camera and shared motion, the
smoothness across videos, and a whole small fit's run directory (s3o_warp.data.store, motion.windows, model, fit)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import smoke_config

from s3o_warp.coarse.model import coarse_model
from s3o_warp.data.store import prepare_data
from s3o_warp.errors import InputError
from s3o_warp.fit import Fitter, fit
from s3o_warp.motion import losses as L
from s3o_warp.motion.hypotheses import ORIENTATION_TILTS
from s3o_warp.motion.windows import FrameWindows, seed_unvisited
from s3o_warp.synth import make_sequence

CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def two_videos(tmp_path_factory) -> list[Path]:
    """The built-in quadruped from its right flank (6 frames, 96 x 72) and its left (5 frames, 128 x 96)."""
    root = tmp_path_factory.mktemp("videos")
    a = make_sequence(root / "right", frames=6, size=(96, 72), azim=(-10.0, 0.0), seed=0, progress=False)
    b = make_sequence(root / "left", frames=5, size=(128, 96), azim=(170.0, 180.0), seed=0, progress=False)
    return [a, b]


def test_several_videos_are_one_sequence_with_no_flow_between_them(two_videos, tmp_path):
    cfg = smoke_config()
    both = prepare_data(two_videos, cfg, tmp_path / "both", CPU)
    alone = [prepare_data(p, cfg, tmp_path / p.name, CPU) for p in two_videos]
    assert both.num_frames == 11 and both.num_videos == 2
    assert [(v.name, v.start, v.stop, v.frame_size) for v in both.videos] == [
        ("right", 0, 6, (72, 96)), ("left", 6, 11, (96, 128))]
    assert both.pair_valid(1).tolist() == [True] * 5 + [False] + [True] * 4
    assert torch.equal(both.masks, torch.cat([a.masks for a in alone]))
    assert torch.equal(both.images[torch.arange(11)], torch.cat([a.images[torch.arange(a.num_frames)] for a in alone]))
    assert torch.equal(both.crop_to_frame, torch.cat([a.crop_to_frame for a in alone]))
    pairs = torch.arange(10)
    flow, conf = both.flow_fwd[pairs], both.conf_fwd[pairs]
    assert torch.equal(flow[:5], alone[0].flow_fwd[torch.arange(5)])
    assert torch.equal(flow[6:], alone[1].flow_fwd[torch.arange(4)])
    assert torch.equal(conf[6:], alone[1].conf_fwd[torch.arange(4)])
    assert float(conf[5].abs().max()) == 0 and float(flow[5].abs().max()) == 0  # the pair joining the two videos
    assert float(conf[:5].max()) > 0


def test_windows_stay_inside_their_video_and_the_sweep_starts_at_each_anchor():
    gen = torch.Generator().manual_seed(0)
    w = FrameWindows(30, 8, canonical=3, generator=gen, device=CPU, videos=[(0, 12), (12, 17), (17, 30)],
                     anchors=[3, 15, 25])
    for _ in range(300):
        fr = w.random().tolist()
        v = w.video(fr[0])
        a, b = w.videos[v]
        assert a <= fr[0] and fr[-1] < b and fr == list(range(fr[0], fr[0] + len(fr)))
        assert len(fr) == min(8, b - a)
    for v in range(3):
        fr = w.random(v)
        assert all(w.video(int(t)) == v for t in fr)
    wins = w.sweep_windows()
    assert wins[:3] == [(0, 8), (12, 5), (21, 8)]  # each video's first window holds its anchor
    assert all(w.video(s) == w.video(s + n - 1) for s, n in wins)


def test_one_video_windows_are_as_before():
    gen_a, gen_b = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    one = FrameWindows(20, 8, canonical=13, generator=gen_a, device=CPU)
    explicit = FrameWindows(20, 8, canonical=13, generator=gen_b, device=CPU, videos=[(0, 20)], anchors=[13])
    assert one.sweep_starts() == explicit.sweep_starts()
    assert [one.random().tolist() for _ in range(20)] == [explicit.random().tolist() for _ in range(20)]


def _fitter(paths, tmp_path, **over):
    cfg = smoke_config(**over)
    data = prepare_data(paths, cfg, tmp_path, CPU)
    return Fitter(data, coarse_model(data, cfg), cfg, tmp_path, CPU), data


def test_each_video_has_its_focal_length_and_synchronized_videos_share_the_pose(two_videos, tmp_path):
    f, data = _fitter(two_videos, tmp_path / "a")
    m = f.model
    assert m.log_focal.shape == (2,) and m.num_motion_rows == 11
    with torch.no_grad():
        m.log_focal[1] += 0.5
        K = m.intrinsics_crop(torch.tensor([0, 7]))
        want = torch.exp(m.log_focal)[[0, 1]] * m.crop_scale[[0, 7]]
    torch.testing.assert_close(K[:, 0, 0], want)
    assert float(m.log_focal.detach()[1] - m.log_focal.detach()[0]) == pytest.approx(0.5 + np.log(128 / 96), rel=1e-5)  # its own width
    # synchronized: frame k of every video takes bone-motion row k
    same = [two_videos[0], two_videos[0]]
    g, _ = _fitter(same, tmp_path / "b", **{"motion.synchronized": True})
    assert g.model.num_motion_rows == 6 and g.model.motion_of.tolist() == list(range(6)) * 2
    with torch.no_grad():
        g.model.bone_aa.normal_(0, 0.1)
    bt = g.model.bone_rt(torch.arange(12))
    assert torch.equal(bt[:6], bt[6:])
    assert not torch.equal(bt[0], bt[1])


def test_smoothness_leaves_out_the_pair_joining_two_videos():
    x = torch.randn(7, 3, requires_grad=True)
    pairs = torch.tensor([True, True, False, True, True, True])
    got = L.temporal_smoothness(x, pairs)
    d = torch.stack([x[t + 1] - x[t] for t in range(6) if pairs[t]])
    torch.testing.assert_close(got, (d ** 2).mean())
    got.backward()
    assert x.grad is not None
    assert L.temporal_smoothness(x) > 0


def test_the_sweep_seeds_a_frame_from_its_own_video(two_videos, tmp_path):
    f, _ = _fitter(two_videos, tmp_path / "c")
    m = f.model
    with torch.no_grad():
        m.root_t.copy_(torch.arange(11, dtype=torch.float32)[:, None].expand(11, 3))
    m.visited.zero_()
    seed_unvisited(m, torch.tensor([5, 6, 7]), canonical=2, videos=[(0, 6), (6, 11)], anchors=[2, 9])
    # frame 5 from frame 2 (its video's anchor), frames 6 and 7 from frame 9 (not from frame 5 next door)
    assert m.root_t[5, 0] == 2 and m.root_t[6, 0] == 9 and m.root_t[7, 0] == 9


def test_a_fit_of_two_videos_writes_each_videos_run_and_one_glb(two_videos, tmp_path):
    pygltflib = pytest.importorskip("pygltflib")
    run = tmp_path / "run"
    metrics = fit(two_videos, run, smoke_config(), CPU)
    assert set(metrics["videos"]) == {"right", "left"}
    for name in ("right", "left"):
        sub = run / "videos" / name
        assert (run / f"{name}.usdc").is_file()
        for f in ("motion.npz", "canonical.ply", "skeleton.json", "metrics.json"):
            assert (sub / f).is_file(), f
        with np.load(sub / "motion.npz") as z:
            assert len(z["frame_names"]) == (6 if name == "right" else 5)
            assert tuple(z["image_size"]) == ((72, 96) if name == "right" else (96, 128))
        assert json.loads((sub / "metrics.json").read_text())["mask_iou"]["mean"] == metrics["videos"][name]["mask_iou"]["mean"]
    ious = [metrics["videos"][n]["mask_iou"]["mean"] for n in ("right", "left")]
    assert metrics["mean"]["mask_iou"]["mean"] == pytest.approx(np.mean(ious))
    reg = metrics["registration"]
    assert reg["right"]["yaw_deg"] == 0.0 or reg["left"]["yaw_deg"] == 0.0  # the reference video is not turned
    other = reg["left"] if reg["right"]["yaw_deg"] == 0.0 and not reg["right"]["yaws_deg"] else reg["right"]
    assert len(other["yaws_deg"]) == len(other["tilts_deg"]) == 8 + len(ORIENTATION_TILTS) and "margin" in other
    assert other["tilts_deg"][8:] == list(ORIENTATION_TILTS) and len(set(other["yaws_deg"][8:])) == 1
    assert "tilt_deg" in other
    assert {n: metrics["videos"][n]["registration"] for n in reg} == reg  # each video's own metrics say it too
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert {r["video"] for r in log if r.get("what") == "hypotheses"} == {"right", "left"}  # what a resume reads
    assert json.loads((run / "videos.json").read_text())["videos"] == ["right", "left"]
    glb = pygltflib.GLTF2().load(str(run / "right+left.glb"))
    assert sorted(a.name for a in glb.animations) == ["left", "right"]
    assert not (run / "motion.npz").exists()


def test_bad_several_video_input_is_one_line(two_videos, tmp_path):
    with pytest.raises(InputError, match="as many frames"):
        fit(two_videos, tmp_path / "s", smoke_config(**{"motion.synchronized": True}), CPU)
    with pytest.raises(InputError, match="principal_point=shared takes one video"):
        fit(two_videos, tmp_path / "p", smoke_config(**{"motion.principal_point": "shared"}), CPU)
    assert not (tmp_path / "s").exists() and not (tmp_path / "p").exists()


def test_cli_takes_one_masks_folder_per_video(two_videos, tmp_path, capsys):
    from s3o_warp.cli import main

    rc = main([str(two_videos[0]), str(two_videos[1]), "--masks", str(two_videos[0] / "masks"), "--out",
               str(tmp_path / "x"), "--preset", "smoke"])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--masks given 1 times for 2 videos" in err[0]
    assert main([str(two_videos[0]), "--synchronized", "--out", str(tmp_path / "y"), "--preset", "smoke"]) == 2
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()
