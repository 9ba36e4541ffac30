"""s3o_warp.data.flow: crop flow and its forward-backward confidence, DIS's finest level, the on-disk cache."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from data_frames import H, W, rect_mask, shift, texture, write_seq

from s3o_warp.config import DataConfig
from s3o_warp.data import flow as flow_mod
from s3o_warp.data.crops import crop_frame, map_points
from s3o_warp.data.flow import compute_flow, make_dis, pair_flow
from s3o_warp.data.sequence import open_sequence


def fb_confidence_reference(f: torch.Tensor, b: torch.Tensor, sigma: float) -> torch.Tensor:
    """Twin of the definition on crop grids: exp(-|f(x) + b(x + f(x))|^2 / (2 sigma^2)), bilinear b.

    f, b: (S, S, 2) float64 crop flows; returns (S, S) (0 where x + f(x) leaves the grid).
    """
    S = f.shape[0]
    r, c = torch.meshgrid(torch.arange(S, dtype=f.dtype), torch.arange(S, dtype=f.dtype), indexing="ij")
    qx, qy = c + f[..., 0], r + f[..., 1]
    x0, y0 = qx.floor(), qy.floor()
    inside = (x0 >= 0) & (y0 >= 0) & (x0 <= S - 2) & (y0 <= S - 2)
    x0c, y0c = x0.clamp(0, S - 2).long(), y0.clamp(0, S - 2).long()
    wx, wy = (qx - x0)[..., None], (qy - y0)[..., None]
    bq = (
        b[y0c, x0c] * (1 - wx) * (1 - wy)
        + b[y0c, x0c + 1] * wx * (1 - wy)
        + b[y0c + 1, x0c] * (1 - wx) * wy
        + b[y0c + 1, x0c + 1] * wx * wy
    )
    return torch.exp(-((f + bq) ** 2).sum(-1) / (2 * sigma**2)) * inside


def translated_pair(d=(2.6, -1.4), h=120, w=160):
    img0 = texture(h, w, seed=3)
    img1 = shift(img0, *d)
    m0 = rect_mask(50, 30, 109, 89, h, w) > 0
    m1 = rect_mask(52, 29, 112, 88, h, w) > 0  # boxes of the two frames differ: crops differ
    return img0, img1, m0, m1


@pytest.mark.parametrize("crop_size", [64, 96])
def test_flow_on_translated_texture(crop_size):
    d = np.array([2.6, -1.4])
    img0, img1, m0, m1 = translated_pair(tuple(d))
    c0 = crop_frame(img0, m0, crop_size, 1.3)
    c1 = crop_frame(img1, m1, crop_size, 1.3)
    arr = pair_flow(img0, img1, c0.crop_to_frame, c1.crop_to_frame, crop_size, 1.0, make_dis("medium"))
    fwd, bwd, cf, cb = arr[..., 0:2], arr[..., 2:4], arr[..., 4], arr[..., 5]
    r, c = np.mgrid[0:crop_size, 0:crop_size].astype(np.float64)
    p = np.stack([c, r], -1)
    true_fwd = map_points(map_points(p, c0.crop_to_frame) + d, c1.frame_to_crop) - p
    true_bwd = map_points(map_points(p, c1.crop_to_frame) - d, c0.frame_to_crop) - p
    err_f = np.linalg.norm(fwd - true_fwd, axis=-1)[c0.mask].mean()
    err_b = np.linalg.norm(bwd - true_bwd, axis=-1)[c1.mask].mean()
    assert err_f < 0.5 and err_b < 0.5, (err_f, err_b)
    # the crops differ (box shift + scale), so the crop flow is not the frame flow: the test can fail
    assert np.linalg.norm(true_fwd - d, axis=-1)[c0.mask].mean() > 0.5
    assert cf[c0.mask].mean() > 0.9 and cb[c1.mask].mean() > 0.9
    # confidence agrees with the definition evaluated on the crop grids (twin), where the flow is smooth
    ref = fb_confidence_reference(torch.tensor(fwd, dtype=torch.float64), torch.tensor(bwd, dtype=torch.float64), 1.0)
    inner = c0.mask & (ref.numpy() > 0)
    assert np.abs(cf[inner] - ref.numpy()[inner]).mean() < 0.05


def test_flow_confidence_low_where_occluded():
    """A textured square slides 6 px right over a static background: the background strip it covers
    (seen at t, hidden at t+1) and the strip it uncovers get low confidence; its interior stays high."""
    h, w, mv = 120, 160, 6
    bg, fg = texture(h, w, seed=3), texture(40, 40, seed=11)
    img0, img1 = bg.copy(), bg.copy()
    img0[40:80, 40:80] = fg
    img1[40:80, 40 + mv : 80 + mv] = fg
    m0, m1 = np.zeros((h, w), bool), np.zeros((h, w), bool)
    m0[40:80, 40:80] = True
    m1[40:80, 40 + mv : 80 + mv] = True
    S = 80
    c0, c1 = crop_frame(img0, m0, S, 1.6), crop_frame(img1, m1, S, 1.6)
    arr = pair_flow(img0, img1, c0.crop_to_frame, c1.crop_to_frame, S, 1.0, make_dis("medium"))
    conf_fwd, conf_bwd = arr[..., 4], arr[..., 5]
    r, c = np.mgrid[0:S, 0:S].astype(np.float64)
    x0 = map_points(np.stack([c, r], -1), c0.crop_to_frame)  # frame points of crop-t pixels
    x1 = map_points(np.stack([c, r], -1), c1.crop_to_frame)

    def box(x, lo_x, hi_x, lo_y=44, hi_y=75):
        return (x[..., 0] > lo_x) & (x[..., 0] < hi_x) & (x[..., 1] > lo_y) & (x[..., 1] < hi_y)

    covered, uncovered = box(x0, 81, 80 + mv - 1), box(x1, 41, 40 + mv - 1)
    assert covered.sum() > 100 and uncovered.sum() > 100
    assert conf_fwd[covered].mean() < 0.4, conf_fwd[covered].mean()
    assert conf_bwd[uncovered].mean() < 0.4, conf_bwd[uncovered].mean()
    assert conf_fwd[box(x0, 46, 74, 46, 74)].mean() > 0.95
    assert conf_bwd[box(x1, 46 + mv, 74 + mv, 46, 74)].mean() > 0.95
    assert conf_fwd.min() >= 0 and conf_fwd.max() <= 1
    # the background moves by 0 in the frame but by a crop-dependent amount in crop pixels
    far = box(x0, 0, 30, 10, 110)
    true_bg = map_points(x0, c1.frame_to_crop) - np.stack([c, r], -1)
    assert np.linalg.norm(arr[..., 0:2] - true_bg, axis=-1)[far].mean() < 0.5


def test_finest_scale_undoes_small_part_bias():
    """A small textured part moving over a still background (a leg in a low-resolution crop): DIS at the medium
    preset's finest level (half resolution) sees it move 10-15 % too little; level 0 (``FLOW_FINEST_SCALE``) within
    5 %."""
    H = W = 96
    yy, xx = np.mgrid[0:H, 0:W]
    d = np.array([1.5, -0.8])
    assert make_dis("medium").getFinestScale() == 1 and make_dis("medium", 0).getFinestScale() == 0
    for seed in range(3):
        tex = texture(H, W, seed=seed)

        def frame(cx, cy):
            m = (xx - cx) ** 2 + (yy - cy) ** 2 < 36
            return cv2.cvtColor(np.where(m[..., None], shift(tex, cx - 48, cy - 48), 90).astype(np.uint8),
                                cv2.COLOR_RGB2GRAY), m

        (a, part), (b, _) = frame(48.0, 48.0), frame(48.0 + d[0], 48.0 + d[1])
        ratio = {fs: float(np.median(make_dis("medium", fs).calc(a, b, None)[part] @ d / (d @ d))) for fs in (None, 0)}
        assert ratio[None] < 0.9 and 0.94 < ratio[0] < 1.06, ratio


def test_compute_flow_cache_hit(tmp_path, monkeypatch):
    root = write_seq(tmp_path / "s", n=3)
    cfg = DataConfig(crop_size=32, flow_preset="fast")
    seq = open_sequence(root, cfg=cfg)
    cache = tmp_path / "run" / "cache"
    fc = compute_flow(seq, cache)
    assert (fc.computed, fc.hits, len(fc)) == (2, 0, 2)
    assert sorted(p.name for p in cache.iterdir()) == sorted(f.name for f in fc.files)  # no temp files left
    assert all(f.name.startswith("flow_") and f.suffix == ".npy" for f in fc.files)
    mtimes = [f.stat().st_mtime_ns for f in fc.files]
    pair = fc[1]
    assert pair.flow_fwd.shape == (32, 32, 2) and pair.conf_bwd.shape == (32, 32)
    assert isinstance(pair.flow_fwd.base, np.memmap) or isinstance(pair.flow_fwd, np.memmap)
    c2f = seq.crop_to_frame
    dis = make_dis("fast", flow_mod.FLOW_FINEST_SCALE)
    direct = pair_flow(seq.image(1), seq.image(2), c2f[1], c2f[2], 32, flow_mod.FLOW_FB_SIGMA, dis)
    np.testing.assert_array_equal(np.asarray(pair.flow_fwd), direct[..., 0:2])

    seq2 = open_sequence(root, cfg=cfg)
    fc2 = compute_flow(seq2, cache)
    assert (fc2.computed, fc2.hits) == (0, 2) and fc2.files == fc.files
    assert [f.stat().st_mtime_ns for f in fc2.files] == mtimes
    # changed content or settings: new keys
    cv2.imwrite(str(root / "images" / "00002.png"), texture(H, W, seed=5))
    fc3 = compute_flow(open_sequence(root, cfg=cfg), cache)
    assert (fc3.computed, fc3.hits) == (1, 1)
    with monkeypatch.context() as mp:
        mp.setattr(flow_mod, "FLOW_FB_SIGMA", 2.0)
        assert compute_flow(seq2, cache).computed == 2
    other = 1 if flow_mod.FLOW_FINEST_SCALE != 1 else 0  # another finest level than the default's
    with monkeypatch.context() as mp:
        mp.setattr(flow_mod, "FLOW_FINEST_SCALE", other)
        fc5 = compute_flow(seq2, cache)
    assert fc5.computed == 2 and not set(fc5.files) & set(fc.files)
    direct = pair_flow(seq2.image(1), seq2.image(2), c2f[1], c2f[2], 32, 1.0, make_dis("fast", other))
    np.testing.assert_array_equal(np.asarray(fc5[1].flow_fwd), direct[..., 0:2])
    # a damaged cache file is recomputed, not trusted
    fc.files[0].write_bytes(b"junk")
    assert compute_flow(seq2, cache).computed == 1


def test_a_stop_request_ends_the_flow_between_pairs_and_keeps_the_pairs_done(tmp_path, monkeypatch):
    from s3o_warp import interrupt

    root = write_seq(tmp_path / "s", n=4)
    seq = open_sequence(root, cfg=DataConfig(crop_size=32, flow_preset="fast"))
    cache = tmp_path / "cache"
    orig, calls = flow_mod.pair_flow, []

    def stop_after_first(*args, **kwargs):
        calls.append(1)
        interrupt.request()  # as Ctrl-C does while this pair is computed
        return orig(*args, **kwargs)

    monkeypatch.setattr(flow_mod, "pair_flow", stop_after_first)
    with interrupt.on_signals():
        with pytest.raises(interrupt.Interrupted, match=r"optical flow \(1 of 3 pairs cached\)"):
            compute_flow(seq, cache)
    assert len(calls) == 1 and len(list(cache.glob("flow_*.npy"))) == 1
    monkeypatch.setattr(flow_mod, "pair_flow", orig)
    with interrupt.on_signals():  # a new run: the request is forgotten, the pair done is not computed again
        fc = compute_flow(seq, cache)
    assert (fc.computed, fc.hits) == (2, 1)
