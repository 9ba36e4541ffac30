"""s3o-masks and s3o-fit --box: the sequence folder, its preview and record, every bad input as one line with
nothing written, interruption, and a fit from a box."""

from __future__ import annotations

import json
import os
import signal

import cv2
import numpy as np
import pytest

from s3o_warp.cli import main as fit_main
from s3o_warp.data.sequence import open_sequence
from s3o_warp.errors import InputError
from s3o_warp.masks import make
from s3o_warp.masks.cli import main as masks_main
from s3o_warp.masks.grabcut import MAX_HIDDEN, Frame
from s3o_warp.masks.make import FLAG_BELOW, make_masks, parse_box, parse_box_at, preview_frame
from test_masks_grabcut import behind_a_post, box_of, iou, scene


def write_video(path, images, fps=12.0):
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (images[0].shape[1], images[0].shape[0]))
    for im in images:
        vw.write(cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
    vw.release()
    return path


def write_frames(folder, images):
    folder.mkdir(parents=True)
    for k, im in enumerate(images):
        cv2.imwrite(str(folder / f"f{k:03d}.png"), cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
    return folder


@pytest.fixture(scope="module")
def clip():
    return scene()


def test_masks_from_a_frame_folder_make_a_sequence_the_fit_opens(clip, tmp_path):
    images, truth = clip
    out = make_masks(write_frames(tmp_path / "frames", images), tmp_path / "seq", {4: box_of(truth[4])})
    names = sorted(p.name for p in (out / "images").iterdir())
    assert names == [f"f{k:03d}.png" for k in range(len(images))]  # the frames as they were, names kept
    assert (out / "masks_preview.mp4").stat().st_size > 0 or (out / "masks_preview.gif").is_file()
    seq = open_sequence(out)
    assert seq.num_frames == len(images)
    assert min(iou(seq.mask(k), truth[k]) for k in range(len(images))) > 0.85
    rec = json.loads((out / "masks.json").read_text())
    assert rec["request"]["boxes"] == {"4": list(box_of(truth[4]))} and rec["frames"] == len(images)
    assert rec["mask_pixels"] == [int(seq.mask(k).sum()) for k in range(len(images))]


def test_the_cli_segments_a_video_and_keeps_its_frame_rate(clip, tmp_path, capsys):
    images, truth = clip
    video = write_video(tmp_path / "clip.avi", images)
    x0, y0, x1, y1 = box_of(truth[0])
    assert masks_main([str(video), "--box", f"{x0},{y0},{x1},{y1}", "--out", str(tmp_path / "seq")]) == 0
    rec = json.loads((tmp_path / "seq" / "masks.json").read_text())
    assert rec["fps"] == pytest.approx(12.0) and len(list((tmp_path / "seq" / "masks").iterdir())) == len(images)


@pytest.mark.parametrize("args, words", [
    (["--box", "10,10,60"], "X0,Y0,X1,Y1"),
    (["--box", "60,10,10,50"], "is empty"),
    (["--box", "10,10,60,500"], "outside the 128x96 frame"),
    (["--box", "10,10,60,50", "--frame", "10"], "frame 10 is out of range: the video has 10 frames"),
    (["--box", "0,0,127,95"], "the whole frame"),
    (["--box", "10,10,13,50"], "under 8 pixels"),
    (["--box", "10,10,60,50", "--box-at", "3,10,10,60,50"], "K:X0,Y0,X1,Y1"),
    (["--box", "10,10,60,50", "--box-at", "0:10,10,60,50"], "frame 0 already has a box"),
    (["--frame", "2"], "no box given"),
    (["--box", "10,10,60,50", "--segmenter", "unet"], "choose one of grabcut, sam2"),
    (["--box", "10,10,60,50", "--checkpoint", "w.pt"], "--checkpoint is for --segmenter sam2"),
])
def test_each_bad_input_is_one_line_and_nothing_is_written(clip, tmp_path, capsys, args, words):
    video = write_video(tmp_path / "clip.avi", clip[0])
    rc = masks_main([str(video), "--out", str(tmp_path / "seq"), *args])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("s3o-masks: error: ") and words in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.avi"]


def test_a_folder_not_made_by_s3o_masks_is_never_replaced(clip, tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    video = write_video(tmp_path / "clip.avi", clip[0])
    assert masks_main([str(video), "--box", "20,20,80,70", "--out", str(mine)]) == 2
    assert "was not made by s3o-masks" in capsys.readouterr().err
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]


def test_a_lost_object_names_its_frame_and_the_box_to_add(tmp_path, capsys):
    images, truth = scene(frames=8 + MAX_HIDDEN, vanish_at=5)  # gone for good: not found again after it
    video = write_video(tmp_path / "clip.avi", images)
    x0, y0, x1, y1 = box_of(truth[0])
    assert masks_main([str(video), "--box", f"{x0},{y0},{x1},{y1}", "--out", str(tmp_path / "seq")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the object is lost at frame" in err[0] and "--box-at" in err[0], err
    assert not (tmp_path / "seq").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["clip.avi"]


def test_a_stop_request_leaves_nothing_behind(clip, tmp_path, monkeypatch, capsys):
    images, truth = clip

    def stop_after_one(read, n, boxes, flow_preset):
        yield Frame(0, truth[0], 1.0, False)
        os.kill(os.getpid(), signal.SIGTERM)  # as a user's kill would: the flag, then the next frame's check
        yield Frame(1, truth[1], 1.0, False)
        raise AssertionError("the masks went on after the stop")

    monkeypatch.setattr(make, "segment_video", stop_after_one)
    frames = write_frames(tmp_path / "frames", images)
    assert masks_main([str(frames), "--box", "20,20,80,70", "--out", str(tmp_path / "seq")]) == 130
    assert "nothing was written" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames"]  # no folder, no temporary


def test_doubtful_frames_are_recorded_marked_and_named_with_the_box_to_add(tmp_path, caplog):
    images, truth, _ = behind_a_post()
    frames = write_frames(tmp_path / "frames", images)
    box = box_of(truth[0])
    with caplog.at_level("WARNING", logger="s3o_warp.masks.make"):
        out = make_masks(frames, tmp_path / "seq", {0: box})
    rec = json.loads((out / "masks.json").read_text())
    conf = rec["confidence"]
    assert len(conf) == len(images) and conf[0] == 1.0 and all(0.0 <= c <= 1.0 for c in conf)
    assert set(range(13, 17)) <= set(rec["hidden"]) and all(conf[k] == 0.0 for k in rec["hidden"])
    assert rec["flagged"] == sorted(set(rec["hidden"]) | {k for k, c in enumerate(conf) if c < FLAG_BELOW})
    first = rec["flagged"][0]
    assert 8 <= first <= 12, rec["flagged"]  # the disc going behind the post
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and f"--box-at {first}:X0,Y0,X1,Y1" in warnings[0] and "masks_preview.mp4" in warnings[0]
    assert f"{len(rec['flagged'])} frame(s) may be wrong" in warnings[0], warnings
    # made again from the same video and boxes (s3o-fit --box run again): the same warning, before the fit
    caplog.clear()
    with caplog.at_level("WARNING", logger="s3o_warp.masks.make"):
        make_masks(frames, tmp_path / "seq", {0: box}, reuse=True)
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == warnings


def test_fit_from_a_box_gives_the_warning_before_it_fits(tmp_path, monkeypatch, caplog):
    images, truth, _ = behind_a_post()
    warned = []  # the warnings logged by the time the fit starts

    def fit(*args, **kwargs):
        warned.append([r.getMessage() for r in caplog.records if r.levelname == "WARNING"])
        return {}

    monkeypatch.setattr("s3o_warp.cli.fit", fit)
    box = ",".join(map(str, box_of(truth[0])))
    with caplog.at_level("WARNING", logger="s3o_warp.masks.make"):
        assert fit_main([str(write_frames(tmp_path / "frames", images)), "--box", box, "--out", str(tmp_path / "run"),
                         "--device", "cpu"]) == 0
    assert len(warned) == 1 and any("may be wrong" in m and "--box-at" in m for m in warned[0]), warned


def test_a_clip_with_no_doubt_gives_no_warning(clip, tmp_path, caplog):
    images, truth = clip
    with caplog.at_level("WARNING", logger="s3o_warp.masks.make"):
        out = make_masks(write_frames(tmp_path / "frames", images), tmp_path / "seq", {4: box_of(truth[4])})
    rec = json.loads((out / "masks.json").read_text())
    assert rec["flagged"] == [] and rec["hidden"] == [] and min(rec["confidence"]) >= FLAG_BELOW, rec["confidence"]
    assert not [r for r in caplog.records if r.levelname == "WARNING"]


def test_the_preview_marks_a_flagged_frame():
    image = np.full((96, 128, 3), 90, np.uint8)
    mask = np.zeros((96, 128), bool)
    mask[30:60, 40:80] = True
    plain, flagged = preview_frame(image, mask, 3), preview_frame(image, mask, 3, flag="check")
    assert tuple(flagged[48, 0]) == (255, 0, 0) and tuple(flagged[95, 64]) == (255, 0, 0)
    assert tuple(plain[48, 0]) == (90, 90, 90)


def test_a_box_with_nothing_in_it_is_one_line(tmp_path, capsys):
    images = [np.full((96, 128, 3), 120, np.uint8) for _ in range(4)]  # nothing to tell apart
    frames = write_frames(tmp_path / "frames", images)
    assert masks_main([str(frames), "--box", "20,20,80,70", "--out", str(tmp_path / "seq")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing was segmented in the box 20,20,80,70 on frame 0" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames"]


def test_parsing_boxes():
    assert parse_box(" 1, 2,30.6,40 ") == (1, 2, 31, 40)
    assert parse_box_at("7:1,2,30,40") == (7, (1, 2, 30, 40))
    with pytest.raises(InputError, match="--box-at"):
        parse_box_at("x:1,2,3,4")


def test_fit_from_a_video_and_a_box(clip, tmp_path):
    images, truth = clip
    video = write_video(tmp_path / "clip.avi", images, fps=15.0)
    box = box_of(truth[0])
    run = tmp_path / "run"
    args = [str(video), "--box", ",".join(map(str, box)), "--out", str(run), "--preset", "smoke",
            "--set", "data.crop_size=64", "--set", "motion.batch_frames=4", "--set", "output.render_video=false"]
    assert fit_main(args) == 0
    seq = run / "sequence" / "clip"
    made = [cv2.imread(str(p), 0) > 127 for p in sorted((seq / "masks").iterdir())]
    assert min(iou(a, b) for a, b in zip(made, truth)) > 0.8
    m = json.loads((run / "metrics.json").read_text())
    assert m["frames"] == len(images) and m["mask_iou"]["mean"] > 0.3
    assert np.load(run / "motion.npz")["fps"] == pytest.approx(15.0)  # the video's own rate
    assert (run / "clip.usdc").is_file()  # named after the video
    # the same command again (as --resume does) keeps the masks it made
    stamp = (seq / "masks.json").stat().st_mtime_ns
    assert make_masks(video, seq, {0: box}, reuse=True) == seq
    assert (seq / "masks.json").stat().st_mtime_ns == stamp


def test_fit_refuses_a_box_with_masks_or_without_a_video(tmp_path, capsys):
    assert fit_main(["--box", "1,1,20,20", "--out", str(tmp_path / "r")]) == 2
    assert "needs a video" in capsys.readouterr().err
    assert fit_main([str(tmp_path), "--masks", str(tmp_path), "--box", "1,1,20,20", "--out", str(tmp_path / "r")]) == 2
    assert "leave out --masks" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()
