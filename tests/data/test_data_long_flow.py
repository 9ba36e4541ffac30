"""Long-gap flow (s3o_warp.data.long_flow): direct DIS on hand-made pairs whose true flow is known, composition of
known flows, the per-pixel pick, gap checks and the on-disk cache."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from data_frames import H, W, texture, write_seq

from s3o_warp.config import DataConfig
from s3o_warp.data import long_flow as lf
from s3o_warp.data.crops import crop_frame, map_points, mask_bbox
from s3o_warp.data.flow import FLOW_FINEST_SCALE, make_dis, pair_flow
from s3o_warp.data.sequence import open_sequence
from s3o_warp.errors import ConfigError

S = 96


def _grid(n: int = S) -> np.ndarray:
    r, c = np.mgrid[0:n, 0:n].astype(np.float64)
    return np.stack([c, r], -1)


def _true_crop_flow(motion, c_a, c_b) -> np.ndarray:
    """Crop-a -> crop-b flow of a frame motion x -> motion(x)."""
    p = _grid()
    return map_points(motion(map_points(p, c_a.crop_to_frame)), c_b.frame_to_crop) - p


def _moved(img: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Content moved by the affine map m (2, 3): out(m x) = img(x)."""
    return cv2.warpAffine(img, m, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


@pytest.mark.parametrize("kind", ["translation", "rotation"])
def test_direct_flow_of_a_known_motion(kind):
    """A textured object on a black background moved by a known translation or rotation: the object-only DIS flow
    is the true crop flow."""
    h, w = 120, 160
    m0 = np.zeros((h, w), np.uint8)
    cv2.ellipse(m0, (80, 60), (34, 24), 10, 0, 360, 255, -1)
    img0 = texture(h, w, seed=3) * (m0[..., None] > 0)
    if kind == "translation":
        m = np.array([[1.0, 0, 5.3], [0, 1.0, -3.6]])
    else:  # 6 degrees about a point near the object's centre
        m = cv2.getRotationMatrix2D((82.0, 58.0), 6.0, 1.0)
    img1 = _moved(img0, m)
    m1 = _moved(m0, m) > 127
    m0 = m0 > 0
    c0 = crop_frame(img0, m0, S, 1.6)
    c1 = c0  # one crop for both frames: the crop flow is the frame's motion (crops that follow the mask cancel most)
    dis = make_dis("medium", FLOW_FINEST_SCALE)
    arr = lf.object_pair_flow(img0, img1, m0, m1, mask_bbox(m0), mask_bbox(m1), c0.crop_to_frame, c1.crop_to_frame, S,
                              dis)
    true = _true_crop_flow(lambda x: x @ m[:, :2].T + m[:, 2], c0, c1)
    inner = cv2.erode(c0.mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    err = np.linalg.norm(arr[..., 0:2] - true, axis=-1)[inner]
    assert np.median(err) < 0.3 and err.mean() < 0.6, (np.median(err), err.mean())
    assert np.linalg.norm(true, axis=-1)[inner].mean() > 10 * err.mean()  # a zero flow fails by far
    assert arr[..., 4][inner].mean() > 0.8
    # the blanked background's flow is meaningless: no confidence there (crop corners, 25 % of the crop)
    r, c = np.mgrid[0:S, 0:S]
    corners = np.minimum(r, S - 1 - r) + np.minimum(c, S - 1 - c) < S // 4
    assert not c0.mask[corners].any() and (arr[..., 4][corners] == 0).all() and (arr[..., 5][corners] == 0).all()


def test_object_only_blanks_beyond_the_margin():
    img = np.full((20, 30, 3), 200, np.uint8)
    mask = np.zeros((20, 30), bool)
    mask[8:12, 10:15] = True
    out = lf.object_only(img, mask, margin=2)
    assert out.shape == (20, 30) and (out[6:14, 8:17] == 200).all()  # the mask and 2 px around it, grey
    assert out[5, 12] == 0 and out[10, 7] == 0 and out[0, 0] == 0


def test_object_canvas_covers_both_boxes():
    c2f = np.array([[0.8, 0, 10.0], [0, 0.8, 5.0], [0, 0, 1]])  # crops finer than the frame: canvas at frame scale
    g2f, (hc, wc) = lf.object_canvas((40, 30, 90, 70), (50, 20, 100, 60), c2f, c2f, (120, 160), margin=3)
    assert g2f[0, 0] == 1.0 and (g2f[0, 2], g2f[1, 2]) == (37.0, 17.0)  # first pixel centre: box corner - margin
    assert (wc, hc) == (100 - 40 + 7, 70 - 20 + 7)


def _pair(fwd, bwd, cf, cb) -> np.ndarray:
    arr = np.zeros((S, S, 6), np.float32)
    arr[..., 0:2], arr[..., 2:4], arr[..., 4], arr[..., 5] = fwd, bwd, cf, cb
    return arr


def test_composition_of_two_known_flows():
    """f1 a translation, f2 an affine field: the chain is f1 + f2(p + f1) exactly (bilinear samples of an affine
    field are exact), confidences multiply, and a first hop leaving the middle crop gives confidence 0."""
    p = _grid().astype(np.float32)
    t1 = np.array([2.5, -1.25], np.float32)
    A = np.array([[0.02, -0.05], [0.04, 0.01]], np.float32)
    b2 = np.array([1.0, 0.5], np.float32)
    f1 = np.broadcast_to(t1, (S, S, 2))
    f2 = p @ A.T + b2
    first = _pair(f1, -f1, 0.5, 0.9)
    second = _pair(f2, np.broadcast_to(-b2, (S, S, 2)), 0.8, 0.6)
    out = lf.compose_pairs(first, second)
    expect = t1 + (p + t1) @ A.T + b2
    inner = (slice(4, S - 4), slice(4, S - 4))
    np.testing.assert_allclose(out[..., 0:2][inner], expect[inner], atol=1e-4)
    np.testing.assert_allclose(out[..., 4][inner], 0.4, atol=1e-6)
    # backward: second's backward (-b2), then first's (-t1) at q - b2
    np.testing.assert_allclose(out[..., 2:4][inner], np.broadcast_to(-b2 - t1, (S - 8, S - 8, 2)), atol=1e-5)
    np.testing.assert_allclose(out[..., 5][inner], 0.6 * 0.9, atol=1e-6)
    # the first hop sends column S-1 to S + 1.5: outside the middle crop
    assert (out[:, S - 1, 4] == 0).all() and (out[:, S - 2, 4] == 0).all()


def test_composed_translations_match_the_direct_flow():
    """Two DIS hops of 3 px chained give the 6 px translation (crops identical: crop flow = frame flow)."""
    h, w = 120, 160
    img = [_moved(texture(h, w, seed=4), np.array([[1.0, 0, 3.0 * k], [0, 1.0, 1.5 * k]])) for k in range(3)]
    mask = np.zeros((h, w), bool)
    mask[25:95, 45:115] = True
    c = crop_frame(img[0], mask, S, 1.3).crop_to_frame
    dis = make_dis("medium", FLOW_FINEST_SCALE)
    hops = [pair_flow(img[k], img[k + 1], c, c, S, 1.0, dis) for k in range(2)]
    out = lf.compose_pairs(hops[0], hops[1])
    a = c[0, 0]
    inner = (slice(20, S - 20), slice(20, S - 20))
    np.testing.assert_allclose(out[..., 0:2][inner].mean((0, 1)), [6.0 / a, 3.0 / a], atol=0.1)
    np.testing.assert_allclose(out[..., 2:4][inner].mean((0, 1)), [-6.0 / a, -3.0 / a], atol=0.1)
    assert out[..., 4][inner].mean() > 0.8


def test_pick_takes_the_more_confident_per_pixel_and_direction():
    direct = _pair(1.0, 2.0, 0.0, 0.0)
    composed = _pair(5.0, 6.0, 0.5, 0.5)
    direct[:10, :, 4] = 0.9  # direct forward better in the top rows
    direct[:, :10, 5] = 0.7  # direct backward better in the left columns
    out = lf.pick_pairs(direct, composed)
    assert (out[:10, :, 0:2] == 1.0).all() and (out[10:, :, 0:2] == 5.0).all()
    assert (out[:10, :, 4] == np.float32(0.9)).all() and (out[10:, :, 4] == 0.5).all()
    assert (out[:, :10, 2:4] == 2.0).all() and (out[:, 10:, 2:4] == 6.0).all()
    assert (out[:, :10, 5] == np.float32(0.7)).all()


@pytest.mark.parametrize("gaps, match", [((2, 4), "include 1"), ((1, 2, 5), "gap 5"), ((0, 1), ">= 1")])
def test_bad_gaps_are_one_line(gaps, match):
    with pytest.raises(ConfigError, match=match) as info:
        lf.hop_split(gaps)
    assert "\n" not in str(info.value)


def test_hop_split_and_default_gaps():
    assert lf.hop_split((1, 2, 4, 8)) == {2: (1, 1), 4: (2, 2), 8: (4, 4)}
    assert lf.hop_split((1, 2, 3)) == {2: (1, 1), 3: (2, 1)}
    assert lf.default_gaps(48) == (1, 2, 4, 8, 16, 32) and lf.default_gaps(9) == (1, 2, 4, 8)


def test_compute_long_flow_values_and_cache_hit(tmp_path):
    root = write_seq(tmp_path / "s", n=6)
    cfg = DataConfig(crop_size=32, flow_preset="fast")
    seq = open_sequence(root, cfg=cfg)
    cache = tmp_path / "run" / "cache"
    lc = lf.compute_long_flow(seq, cache, gaps=(1, 2, 4, 8))
    assert lc.gaps == (1, 2, 4)  # 8 is not shorter than the clip: left out
    assert (lc.computed, lc.hits) == (4 + 2, 0)
    assert [len(lc.files[g]) for g in lc.gaps] == [5, 4, 2]
    assert sorted(p.name for p in cache.iterdir()) == sorted(f.name for g in lc.gaps for f in lc.files[g])
    # the cached pair is the chain of its two cached half gaps, picked against direct DIS up to DIRECT_MAX_GAP
    assert lf.DIRECT_MAX_GAP == 2
    dis = make_dis("fast", FLOW_FINEST_SCALE)
    for g, t in ((2, 1), (4, 1)):
        h = g // 2
        expect = lf.compose_pairs(np.load(lc.files[h][t]), np.load(lc.files[h][t + h]))
        if g == 2:
            direct = lf.direct_pair(seq, t, t + g, dis)
            assert not np.array_equal(expect, direct)
            expect = lf.pick_pairs(direct, expect)
        np.testing.assert_array_equal(np.load(lc.files[g][t]), expect)
    pair = lc.pair(0, 4)
    assert pair.flow_fwd.shape == (32, 32, 2) and isinstance(pair.flow_fwd.base, np.memmap)
    mtimes = {f: f.stat().st_mtime_ns for g in lc.gaps for f in lc.files[g]}
    lc2 = lf.compute_long_flow(open_sequence(root, cfg=cfg), cache, gaps=(1, 2, 4))
    assert (lc2.computed, lc2.hits) == (0, 6) and lc2.files == lc.files
    assert {f: f.stat().st_mtime_ns for g in lc2.gaps for f in lc2.files[g]} == mtimes
    # a frame changed: every pair spanning it is new, the others are hits
    cv2.imwrite(str(root / "images" / "00003.png"), texture(H, W, seed=5))
    lc3 = lf.compute_long_flow(open_sequence(root, cfg=cfg), cache, gaps=(1, 2, 4))
    assert (lc3.computed, lc3.hits) == (3 + 2, 1)  # gap 2: (1,3), (2,4), (3,5) new, (0,2) kept; gap 4: both span 3


def test_a_stop_request_ends_the_long_flow_between_pairs_and_keeps_the_pairs_done(tmp_path, monkeypatch):
    from s3o_warp import interrupt

    root = write_seq(tmp_path / "s", n=5)
    seq = open_sequence(root, cfg=DataConfig(crop_size=32, flow_preset="fast"))
    cache = tmp_path / "cache"
    orig, calls = lf.compose_pairs, []

    def stop_after_first(*args, **kwargs):
        calls.append(1)
        interrupt.request()  # as Ctrl-C does while this pair is computed
        return orig(*args, **kwargs)

    monkeypatch.setattr(lf, "compose_pairs", stop_after_first)
    with interrupt.on_signals():
        with pytest.raises(interrupt.Interrupted, match=r"long-gap flow \(1 of 4 pairs cached\)"):
            lf.compute_long_flow(seq, cache, gaps=(1, 2, 4))
    assert len(calls) == 1 and len(list(cache.glob("lflow_*.npy"))) == 1
    monkeypatch.setattr(lf, "compose_pairs", orig)
    with interrupt.on_signals():  # a new run: the pair done is not computed again
        lc = lf.compute_long_flow(seq, cache, gaps=(1, 2, 4))
    assert (lc.computed, lc.hits) == (3, 1)
