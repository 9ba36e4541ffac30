"""s3o_warp.data.crops: the crop transform, resampling (bilinear, anti-aliased, padded), points and intrinsics."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from data_frames import H, W, rect_mask, write_seq

from s3o_warp.data.crops import (
    crop_frame,
    crop_transform,
    intrinsics_crop_to_frame,
    intrinsics_frame_to_crop,
    map_points,
    mask_bbox,
)
from s3o_warp.data.sequence import open_sequence


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
