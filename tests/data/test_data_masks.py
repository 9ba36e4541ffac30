"""s3o_warp.data.masks: palette, label and colour masks, object ids, the largest component."""

from __future__ import annotations

import cv2
import numpy as np
from data_frames import H, W, write_seq
from PIL import Image

from s3o_warp.config import DataConfig
from s3o_warp.data.masks import largest_component
from s3o_warp.data.sequence import open_sequence


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


def test_largest_component():
    m = np.zeros((20, 20), bool)
    m[1:4, 1:4] = True
    m[10:18, 8:15] = True
    big = largest_component(m)
    assert big.sum() == 56 and big[12, 10] and not big[2, 2]
    assert not largest_component(np.zeros((5, 5), bool)).any()
