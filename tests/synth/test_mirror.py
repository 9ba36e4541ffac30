"""The mirrored copy of a sequence: images and masks flipped left-right, keypoints mirrored about the frame's centre
column, no ground truth; mirrored twice it is the original again."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from s3o_warp.errors import InputError
from s3o_warp.synth import make_sequence
from s3o_warp.synth.sequence import mirror_sequence


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    out = tmp_path_factory.mktemp("mirror") / "quad"
    return make_sequence(out, source="quadruped", frames=3, size=(64, 48), progress=False)


def _pixels(folder):
    return {p.name: np.array(Image.open(p)) for p in sorted(folder.iterdir())}


def test_images_and_masks_are_flipped_and_keypoints_mirrored(rendered, tmp_path):
    out = mirror_sequence(rendered, tmp_path / "mirrored")
    assert out == tmp_path / "mirrored"
    assert sorted(p.name for p in out.iterdir()) == ["images", "keypoints.json", "masks"]  # no ground_truth/
    for sub in ("images", "masks"):
        src, dst = _pixels(rendered / sub), _pixels(out / sub)
        assert list(dst) == list(src) == ["000000.png", "000001.png", "000002.png"]
        for name in src:
            assert dst[name].dtype == src[name].dtype and np.array_equal(dst[name], src[name][:, ::-1])
    kp, kp_m = (json.loads((d / "keypoints.json").read_text()) for d in (rendered, out))
    assert kp_m["names"] == kp["names"] and list(kp_m["frames"]) == list(kp["frames"])
    for name, rows in kp["frames"].items():
        a, b = np.array(rows), np.array(kp_m["frames"][name])
        np.testing.assert_allclose(b[:, 0], 64 - 1 - a[:, 0], atol=1e-9)  # OpenCV centres: column c -> W - 1 - c
        np.testing.assert_array_equal(b[:, 1:], a[:, 1:])
        mask = np.array(Image.open(out / "masks" / f"{name}.png")) > 0
        for x, y, v in b[b[:, 2] == 1]:  # a visible keypoint still lies on the (mirrored) animal (within a pixel)
            c, r = int(np.rint(x)), int(np.rint(y))
            assert mask[max(r - 1, 0):r + 2, max(c - 1, 0):c + 2].any()


def test_mirrored_twice_is_the_original(rendered, tmp_path):
    back = mirror_sequence(mirror_sequence(rendered, tmp_path / "once"), tmp_path / "twice")
    for sub in ("images", "masks"):
        src, dst = _pixels(rendered / sub), _pixels(back / sub)
        assert list(src) == list(dst) and all(np.array_equal(src[k], dst[k]) for k in src)
    kp, kp2 = (json.loads((d / "keypoints.json").read_text()) for d in (rendered, back))
    assert kp2["names"] == kp["names"]
    for name, rows in kp["frames"].items():
        np.testing.assert_allclose(np.array(kp2["frames"][name]), np.array(rows), atol=1e-9)


def test_an_existing_folder_is_kept_unless_overwrite(rendered, tmp_path):
    dst = tmp_path / "mirrored"
    mirror_sequence(rendered, dst)
    with pytest.raises(InputError, match="already exists"):
        mirror_sequence(rendered, dst)
    mirror_sequence(dst, dst, overwrite=True)  # in place: the original again
    assert np.array_equal(_pixels(dst / "images")["000001.png"], _pixels(rendered / "images")["000001.png"])
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folder left
    with pytest.raises(InputError, match="masks"):
        (tmp_path / "bare" / "images").mkdir(parents=True)
        mirror_sequence(tmp_path / "bare", tmp_path / "bare-mirrored")
