"""s3o_warp.data.sequence / video_flow: layouts, crop transforms, flow + confidence, cache, every bad input."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from s3o_warp.data import sequence as video

from s3o_warp.data import flow as video_flow
from s3o_warp.config import DataConfig
from s3o_warp.errors import ConfigError, InputError
from s3o_warp.data.sequence import (
    crop_frame,
    crop_transform,
    intrinsics_crop_to_frame,
    intrinsics_frame_to_crop,
    largest_component,
    map_points,
    mask_bbox,
    open_sequence,
)
from s3o_warp.data.flow import compute_flow, make_dis, pair_flow

H, W = 60, 80

# ------------------------------------------------------------------ synthetic data


def texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """Smooth random RGB texture (uint8): good for optical flow."""
    rng = np.random.default_rng(seed)
    noise = rng.random((h // 4 + 2, w // 4 + 2, 3)).astype(np.float32)
    big = cv2.resize(noise, (w + 8, h + 8), interpolation=cv2.INTER_CUBIC)[4 : 4 + h, 4 : 4 + w]
    return np.clip(big * 255, 0, 255).astype(np.uint8)


def shift(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Content moves by (+dx, +dy): out(x) = img(x - d)."""
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(img, m, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def rect_mask(x0: int, y0: int, x1: int, y1: int, h: int = H, w: int = W) -> np.ndarray:
    m = np.zeros((h, w), np.uint8)
    m[y0 : y1 + 1, x0 : x1 + 1] = 255
    return m


def write_seq(root: Path, n: int = 3, names=None, mask_names=None, ext: str = ".png") -> Path:
    """root/images + root/masks with n textured frames and a moving rectangle mask."""
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    names = names or [f"{k:05d}" for k in range(n)]
    mask_names = mask_names or names
    base = texture(H, W)
    for k, (a, b) in enumerate(zip(names, mask_names)):
        cv2.imwrite(str(root / "images" / f"{a}{ext}"), cv2.cvtColor(shift(base, k, 0), cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(root / "masks" / f"{b}.png"), rect_mask(20 + k, 15, 50 + k, 40))
    return root


def listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def open_and_flow(path, tmp_path: Path, **kw):
    """The whole reading path a run takes; returns the cache folder it would write to."""
    seq = open_sequence(path, **kw)
    return compute_flow(seq, tmp_path / "run" / "cache")


# ------------------------------------------------------------------ layouts


def test_images_masks_layout_and_lazy_reads(tmp_path, monkeypatch):
    monkeypatch.setattr(video, "FRAME_CACHE_SIZE", 2)
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


def test_palette_masks_and_object_id(tmp_path):
    root = write_seq(tmp_path / "p", n=2)
    for k in range(2):
        lab = np.zeros((H, W), np.uint8)
        lab[10:20, 10 + k : 30 + k] = 1
        lab[30:50, 40:70] = 2
        im = Image.fromarray(lab, mode="P")
        im.putpalette([0, 0, 0, 128, 0, 0, 0, 128, 0] + [0] * (256 * 3 - 9))
        im.save(root / "masks" / f"{k:05d}.png")
    any_obj = open_sequence(root, cfg=DataConfig(largest_blob=False))
    np.testing.assert_array_equal(any_obj.bboxes[0], [10, 10, 69, 49])
    largest = open_sequence(root)  # two objects, no id: two blobs, the largest is used (with a warning)
    np.testing.assert_array_equal(largest.bboxes[0], [40, 30, 69, 49])
    obj1 = open_sequence(root, cfg=DataConfig(object_id=1))
    np.testing.assert_array_equal(obj1.bboxes[1], [11, 10, 30, 19])
    assert obj1.mask(1).sum() == 10 * 20
    obj2 = open_sequence(root, cfg=DataConfig(object_id=2))
    np.testing.assert_array_equal(obj2.bboxes[0], [40, 30, 69, 49])


def test_colour_masks_use_the_brightest_channel(tmp_path):
    root = write_seq(tmp_path / "c", n=2)
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[10:30, 5:25] = (0, 0, 128)  # DAVIS-palette dark red, saved as BGR by OpenCV
    cv2.imwrite(str(root / "masks" / "00001.png"), rgb)
    seq = open_sequence(root)
    np.testing.assert_array_equal(seq.bboxes[1], [5, 10, 24, 29])
    assert seq.mask(1).sum() == 400


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


# ------------------------------------------------------------------ crops


def test_crop_transform_formula():
    m = crop_transform((10, 20, 29, 29), crop_size=40, crop_scale=2.0)  # 20 x 10 box -> side 40
    np.testing.assert_allclose(m, [[1, 0, 0], [0, 1, 5], [0, 0, 1]])
    # the crop's edges map to the square's edges
    m = crop_transform((0, 0, 9, 4), crop_size=8, crop_scale=1.5)
    side, a = 15.0, 15.0 / 8
    edges = map_points(np.array([[-0.5, -0.5], [7.5, 7.5]]), m)
    np.testing.assert_allclose(edges, [[4.5 - side / 2, 2 - side / 2], [4.5 + side / 2, 2 + side / 2]])
    assert m[0, 0] == pytest.approx(a)


@pytest.mark.parametrize("crop_size,crop_scale", [(64, 1.2), (32, 1.7), (17, 2.5), (128, 1.0)])
def test_crop_marks_land_where_the_transform_says(crop_size, crop_scale):
    """A Gaussian mark at a known sub-pixel frame point: its crop centroid = frame_to_crop @ point."""
    h, w = 120, 150
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    mask = np.zeros((h, w), bool)
    mask[25:100, 35:90] = True
    a = crop_transform(mask_bbox(mask), crop_size, crop_scale)[0, 0]  # frame pixels per crop pixel
    sigma = max(2.0, 1.2 * a)  # the mark spans a few crop pixels, whatever the scale
    cy, cx = np.mgrid[0:crop_size, 0:crop_size].astype(np.float64)
    centre = (crop_size - 1) / 2  # the box centre (62, 62) lands on the crop's centre, whatever the matrix says
    f2c = np.linalg.inv(crop_transform(mask_bbox(mask), crop_size, crop_scale))
    np.testing.assert_allclose(map_points(np.array([62.0, 62.0]), f2c), [centre, centre])
    for x, y in [[50.3, 45.7], [70.0, 80.25], [61.6, 60.9], [62.0, 62.0]]:  # well inside the mask box
        img = np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma**2)).astype(np.float32)
        crop = crop_frame(np.repeat(img[..., None], 3, axis=2), mask, crop_size, crop_scale)
        np.testing.assert_allclose(crop.frame_to_crop @ crop.crop_to_frame, np.eye(3), atol=1e-12)
        ex, ey = map_points(np.array([x, y]), crop.frame_to_crop)
        win = ((cx - ex) ** 2 + (cy - ey) ** 2) < (4.0 * sigma / a) ** 2
        wgt = crop.image[..., 0].astype(np.float64) * win
        got = np.array([(wgt * cx).sum(), (wgt * cy).sum()]) / wgt.sum()
        np.testing.assert_allclose(got, [ex, ey], atol=0.03)


def test_crop_values_are_bilinear_samples_of_the_frame():
    """On a linear ramp bilinear sampling is exact: crop[r, c] = ramp(crop_to_frame @ (c, r))."""
    h, w = 50, 70
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    ramp = np.stack([2 * xx + 3 * yy + 10, xx, yy], axis=-1).astype(np.float32)
    mask = np.zeros((h, w), bool)
    mask[10:41, 15:46] = True
    crop = crop_frame(ramp, mask, 45, 1.3)  # a < 1: upsampling only, no pyramid
    cy, cx = np.mgrid[0:45, 0:45].astype(np.float64)
    pts = map_points(np.stack([cx, cy], -1), crop.crop_to_frame)
    np.testing.assert_allclose(crop.image[..., 1], pts[..., 0], atol=0.04)
    np.testing.assert_allclose(crop.image[..., 2], pts[..., 1], atol=0.04)


def test_crop_shrinking_is_anti_aliased():
    """A 1-pixel checkerboard shrunk ~4x must come out as flat grey, not as aliasing stripes."""
    yy, xx = np.mgrid[0:200, 0:200]
    board = np.where((xx + yy) % 2 == 0, 255, 0).astype(np.uint8)
    mask = np.zeros((200, 200), bool)
    mask[40:160, 40:160] = True
    crop = crop_frame(np.repeat(board[..., None], 3, axis=2), mask, 32, 1.1)
    assert crop.crop_to_frame[0, 0] > 4
    assert abs(crop.image.mean() - 127.5) < 3 and crop.image.std() < 4


def test_crop_pads_past_the_border_and_flags_it(tmp_path):
    img = np.full((H, W, 3), 200, np.uint8)
    mask = np.zeros((H, W), bool)
    mask[0:20, 0:20] = True  # at the corner: the crop leaves the frame
    crop = crop_frame(img, mask, 40, 2.0, background=(1, 2, 3))
    np.testing.assert_array_equal(crop.image[0, 0], [1, 2, 3])
    np.testing.assert_array_equal(crop.image[-1, -1], [200, 200, 200])
    assert not crop.mask[0, 0] and crop.mask[25, 25]
    root = write_seq(tmp_path / "b", n=2)
    cv2.imwrite(str(root / "masks" / "00001.png"), rect_mask(0, 5, 30, 30))
    seq = open_sequence(root)
    np.testing.assert_array_equal(seq.touches_border, [False, True])


def test_points_and_intrinsics_round_trip():
    m = crop_transform((30, 20, 90, 70), 64, 1.2)
    pts = np.random.default_rng(1).random((10, 2)) * 64
    back = map_points(map_points(pts, m), np.linalg.inv(m))
    np.testing.assert_allclose(back, pts, atol=1e-10)
    # torch and batched transforms agree with numpy
    tp = torch.tensor(pts)
    np.testing.assert_allclose(map_points(tp, m).numpy(), map_points(pts, m))
    stack = np.stack([m, np.linalg.inv(m)])
    np.testing.assert_allclose(map_points(np.stack([pts, pts]), stack)[1], map_points(pts, np.linalg.inv(m)))
    # projecting with K_frame = crop_to_frame @ K_crop equals projecting in the crop then mapping
    K_crop = np.array([[70.0, 0, 31.5], [0, 75.0, 30.0], [0, 0, 1]])
    X = np.random.default_rng(2).random((20, 3)) + [0, 0, 3]
    proj = lambda K: (X @ K.T)[:, :2] / (X @ K.T)[:, 2:]  # noqa: E731
    K_frame = intrinsics_crop_to_frame(K_crop, m)
    np.testing.assert_allclose(proj(K_frame), map_points(proj(K_crop), m), atol=1e-9)
    np.testing.assert_allclose(intrinsics_frame_to_crop(K_frame, np.linalg.inv(m)), K_crop, atol=1e-9)
    Kt = intrinsics_crop_to_frame(torch.tensor(K_crop, dtype=torch.float32), m)
    assert isinstance(Kt, torch.Tensor) and Kt.dtype == torch.float32
    np.testing.assert_allclose(Kt.numpy(), K_frame, rtol=1e-6)


def test_largest_component():
    m = np.zeros((20, 20), bool)
    m[1:4, 1:4] = True
    m[10:18, 8:15] = True
    big = largest_component(m)
    assert big.sum() == 56 and big[12, 10] and not big[2, 2]
    assert not largest_component(np.zeros((5, 5), bool)).any()


# ------------------------------------------------------------------ flow


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
    dis = make_dis("fast", video_flow.FLOW_FINEST_SCALE)
    direct = pair_flow(seq.image(1), seq.image(2), c2f[1], c2f[2], 32, video_flow.FLOW_FB_SIGMA, dis)
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
        mp.setattr(video_flow, "FLOW_FB_SIGMA", 2.0)
        assert compute_flow(seq2, cache).computed == 2
    other = 1 if video_flow.FLOW_FINEST_SCALE != 1 else 0  # another finest level than the default's
    with monkeypatch.context() as mp:
        mp.setattr(video_flow, "FLOW_FINEST_SCALE", other)
        fc5 = compute_flow(seq2, cache)
    assert fc5.computed == 2 and not set(fc5.files) & set(fc.files)
    direct = pair_flow(seq2.image(1), seq2.image(2), c2f[1], c2f[2], 32, 1.0, make_dis("fast", other))
    np.testing.assert_array_equal(np.asarray(fc5[1].flow_fwd), direct[..., 0:2])
    # a damaged cache file is recomputed, not trusted
    fc.files[0].write_bytes(b"junk")
    assert compute_flow(seq2, cache).computed == 1


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
