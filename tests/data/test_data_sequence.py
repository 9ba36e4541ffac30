"""s3o_warp.data.sequence: layouts (folders, DAVIS, video files), lazy reads, every bad input."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from data_frames import H, W, listing, rect_mask, shift, texture, write_seq
from PIL import Image

from s3o_warp.config import DataConfig
from s3o_warp.data import sequence
from s3o_warp.data.flow import compute_flow
from s3o_warp.data.sequence import open_sequence
from s3o_warp.errors import ConfigError, InputError


def open_and_flow(path, tmp_path: Path, **kw):
    """The whole reading path a run takes; returns the cache folder it would write to."""
    seq = open_sequence(path, **kw)
    return compute_flow(seq, tmp_path / "run" / "cache")


# ------------------------------------------------------------------ layouts


def test_images_masks_layout_and_lazy_reads(tmp_path, monkeypatch):
    monkeypatch.setattr(sequence, "FRAME_CACHE_SIZE", 2)
    root = write_seq(tmp_path / "walk", n=4)
    (root / "keypoints.json").write_text("{}")
    (root / "ground_truth").mkdir()
    seq = open_sequence(root, cfg=DataConfig(crop_size=32))
    assert seq.name == "walk" and seq.num_frames == 4 and len(seq) == 4
    assert seq.frame_names == ["00000", "00001", "00002", "00003"]
    assert seq.size == (H, W) and seq.fps == 30.0
    assert seq.keypoints_file == root / "keypoints.json" and seq.ground_truth_dir == root / "ground_truth"
    np.testing.assert_array_equal(seq.bboxes[2], [22, 15, 52, 40])
    img = seq.image(2)
    assert img.dtype == np.uint8 and img.shape == (H, W, 3)
    expect = cv2.cvtColor(cv2.imread(str(root / "images" / "00002.png")), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(img, expect)  # RGB order
    m = seq.mask(2)
    assert m.dtype == bool and m.sum() == 31 * 26
    for k in range(4):
        seq.image(k)
        seq.mask(k)
    assert len(seq._lru) <= 4  # 2 frames x (image, mask): never the whole sequence
    crops = list(seq.crops())
    assert len(crops) == 4 and crops[0].image.shape == (32, 32, 3) and crops[0].mask.shape == (32, 32)
    assert not seq.touches_border.any()


def test_mask_names_differ_pairs_in_natural_order(tmp_path):
    names = ["f1", "f2", "f10"]  # natural order, not lexicographic
    root = write_seq(tmp_path / "s", names=names, mask_names=["m1", "m2", "m10"], ext=".jpg")
    seq = open_sequence(root)
    assert seq.frame_names == ["f1", "f2", "f10"]
    assert [p.name for p in seq.mask_files] == ["m1.png", "m2.png", "m10.png"]
    np.testing.assert_array_equal(seq.bboxes[:, 0], [20, 21, 22])


def test_davis_layouts(shared_data, tmp_path):
    davis = shared_data / "davis"
    by_name = open_sequence(davis, name="cows")
    by_folder = open_sequence(davis / "JPEGImages" / "480p" / "cows")
    by_res = open_sequence(davis / "JPEGImages" / "480p", name="cows")
    for seq in (by_name, by_folder, by_res):
        assert seq.name == "cows" and seq.num_frames == 104 and seq.size == (480, 854)
        assert seq.fps == DataConfig().fps and seq.keypoints_file is None
    assert by_name.mask_files[3] == davis / "Annotations" / "480p" / "cows" / "00003.png"
    np.testing.assert_array_equal(by_name.bboxes, by_folder.bboxes)
    img, m = by_name.image(5), by_name.mask(5)
    assert img.shape == (480, 854, 3) and m.dtype == bool and 0.05 < m.mean() < 0.5
    crop = by_name.crop(5)
    assert crop.mask.mean() > 0.1
    with pytest.raises(InputError, match="no sequence name given.*cows"):
        open_sequence(davis)
    with pytest.raises(InputError, match="unknown sequence 'horse'.*pass name="):
        open_sequence(davis, name="horse")


@pytest.mark.parametrize("fourcc,ext", [("MJPG", ".avi"), ("mp4v", ".mp4")])
def test_video_layout_and_seeking(tmp_path, fourcc, ext):
    n = 14
    video = tmp_path / f"clip{ext}"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*fourcc), 12.0, (W, H))
    assert writer.isOpened()
    base = texture(H, W)
    (tmp_path / "seq" / "masks").mkdir(parents=True)
    for k in range(n):
        writer.write(cv2.cvtColor(shift(base, k, 0), cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(tmp_path / "seq" / "masks" / f"{k:04d}.png"), rect_mask(10 + k, 10, 40 + k, 40))
    writer.release()
    (tmp_path / "seq" / "keypoints.json").write_text("{}")
    seq = open_sequence(video, masks=tmp_path / "seq" / "masks", cfg=DataConfig())
    assert seq.name == "clip" and seq.num_frames == n and seq.size == (H, W) and seq.fps == 12.0
    assert seq.frame_names[0] == "000000" and seq.keypoints_file == tmp_path / "seq" / "keypoints.json"
    in_order = [seq.image(k).astype(int) for k in range(n)]
    seq._lru.clear()
    for k in [9, 2, 13, 0, 7, 8, 3]:  # random access must give the same frames as reading straight on
        np.testing.assert_array_equal(seq.image(k), in_order[k])
        seq._lru.clear()
    # decoded content is the written frame in RGB order (lossy codecs: close, not equal)
    written = shift(base, 5, 0).astype(int)
    err_rgb = np.abs(in_order[5] - written).mean()
    assert err_rgb < 16 and err_rgb < 0.5 * np.abs(in_order[5] - written[..., ::-1]).mean()
    # flow over the video (frames decoded in order), cached on the video's content
    cfg = DataConfig(crop_size=32, flow_preset="ultrafast")
    seq = open_sequence(video, masks=tmp_path / "seq" / "masks", cfg=cfg)
    fc = compute_flow(seq, tmp_path / "run" / "cache")
    assert (fc.computed, len(fc)) == (n - 1, n - 1)
    assert compute_flow(seq, tmp_path / "run" / "cache").hits == n - 1
    seq.close()


# ------------------------------------------------------------------ bad input: one line, file named, nothing written


def assert_bad(path, tmp_path: Path, match: str, names: list[str], **kw):
    data = Path(path) if Path(path).is_dir() else Path(path).parent
    before = listing(data)
    with pytest.raises(InputError, match=match) as info:
        open_and_flow(path, tmp_path, **kw)
    msg = str(info.value)
    assert "\n" not in msg
    for name in names:
        assert str(name) in msg, (name, msg)
    assert not (tmp_path / "run").exists()
    assert listing(data) == before
    return msg


def test_bad_missing_folders(tmp_path):
    assert_bad(tmp_path / "nope", tmp_path, "no such file or folder", [tmp_path / "nope"])
    (tmp_path / "empty").mkdir()
    assert_bad(tmp_path / "empty", tmp_path, "no images/ and masks/", [tmp_path / "empty"])
    root = write_seq(tmp_path / "s", n=2)
    for f in (root / "masks").iterdir():
        f.unlink()
    (root / "masks").rmdir()
    assert_bad(root, tmp_path, "mask folder not found", [root / "masks"])


def test_bad_unreadable_files(tmp_path):
    root = write_seq(tmp_path / "a", n=3)
    (root / "images" / "00001.png").write_bytes(b"not a png")
    assert_bad(root, tmp_path, "cannot read this image", [root / "images" / "00001.png"])
    root = write_seq(tmp_path / "b", n=3)
    (root / "masks" / "00002.png").write_bytes(b"")
    assert_bad(root, tmp_path, "cannot read this mask", [root / "masks" / "00002.png"])


def test_bad_counts_and_sizes(tmp_path):
    root = write_seq(tmp_path / "a", n=3)
    (root / "masks" / "00002.png").unlink()
    assert_bad(root, tmp_path, "has 3 frames but .* has 2 masks", [root / "images", root / "masks"])
    root = write_seq(tmp_path / "b", n=3)
    cv2.imwrite(str(root / "masks" / "00001.png"), np.full((H + 2, W, 1), 255, np.uint8))
    assert_bad(root, tmp_path, f"mask size {W}x{H + 2} differs .* {W}x{H}", [root / "masks" / "00001.png"])
    root = write_seq(tmp_path / "c", n=3)
    cv2.imwrite(str(root / "images" / "00002.png"), texture(H, W + 4))
    assert_bad(root, tmp_path, f"size {W + 4}x{H} differs .* {W}x{H}", [root / "images" / "00002.png"])
    root = write_seq(tmp_path / "d", n=1)
    assert_bad(root, tmp_path, "at least 2 frames", [root / "images"])
    root = write_seq(tmp_path / "e", n=2)
    for f in (root / "images").iterdir():
        f.unlink()
    for f in (root / "masks").iterdir():
        f.unlink()
    assert_bad(root, tmp_path, "no frames found", [root / "images"])


def test_bad_mask_content(tmp_path):
    root = write_seq(tmp_path / "a", n=3)
    cv2.imwrite(str(root / "masks" / "00001.png"), np.zeros((H, W), np.uint8))
    msg = assert_bad(root, tmp_path, "mask is empty", [root / "masks" / "00001.png"])
    assert "remove this frame" in msg and "fix the mask" in msg
    root = write_seq(tmp_path / "b", n=3)
    cv2.imwrite(str(root / "masks" / "00000.png"), np.full((H, W), 255, np.uint8))
    assert_bad(root, tmp_path, "all foreground", [root / "masks" / "00000.png"])
    root = write_seq(tmp_path / "c", n=2)
    lab = np.zeros((H, W), np.uint8)
    lab[10:20, 10:20] = 1
    Image.fromarray(lab, mode="P").save(root / "masks" / "00001.png")
    Image.fromarray(lab, mode="P").save(root / "masks" / "00000.png")
    msg = assert_bad(
        root, tmp_path, "no pixel with object id 3 \\(ids present: 0, 1\\)", [root / "masks" / "00000.png"],
        cfg=DataConfig(object_id=3),
    )
    assert "data.object_id" in msg


def test_bad_video(tmp_path):
    (tmp_path / "masks").mkdir()
    for k in range(3):
        cv2.imwrite(str(tmp_path / "masks" / f"{k}.png"), rect_mask(10, 10, 30, 30))
    junk = tmp_path / "clip.mp4"
    junk.write_bytes(os.urandom(2000))
    assert_bad(junk, tmp_path, "OpenCV cannot (open|decode)", [junk], masks=tmp_path / "masks")
    assert_bad(junk, tmp_path, "needs its mask folder", [junk])
    good = tmp_path / "ok.avi"
    writer = cv2.VideoWriter(str(good), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, H))
    for k in range(5):
        writer.write(texture(H, W, seed=k))
    writer.release()
    assert_bad(good, tmp_path, "has 5 frames but .* has 3 masks", [good, tmp_path / "masks"], masks=tmp_path / "masks")


def test_bad_settings(tmp_path):
    root = write_seq(tmp_path / "a", n=2)
    for kw, key in [
        ({"crop_size": 4}, "data.crop_size"),
        ({"crop_scale": 0.5}, "data.crop_scale"),
        ({"flow_preset": "slow"}, "data.flow_preset"),
        ({"object_id": -1}, "data.object_id"),
    ]:
        with pytest.raises(ConfigError, match=key):
            open_and_flow(root, tmp_path, cfg=DataConfig(**kw))
    seq = open_sequence(root)
    with pytest.raises(ConfigError, match="open the sequence with the same DataConfig"):
        compute_flow(seq, tmp_path / "run" / "cache", DataConfig(crop_size=64))
    assert not (tmp_path / "run").exists()
