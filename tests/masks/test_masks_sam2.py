"""The optional SAM 2 segmenter: its checks without the package, and its video path on a model built without weights
where the sam2 package is installed (``pip install 's3o-warp[sam2]'``)."""

from __future__ import annotations

from pathlib import Path

import cv2
import pytest

from s3o_warp.errors import InputError
from s3o_warp.masks import sam2
from test_masks_grabcut import box_of, scene


@pytest.mark.parametrize("name, config", [
    ("sam2.1_hiera_tiny.pt", "configs/sam2.1/sam2.1_hiera_t.yaml"),
    ("sam2.1_hiera_base_plus.pt", "configs/sam2.1/sam2.1_hiera_b+.yaml"),
    ("sam2_hiera_large.pt", "configs/sam2/sam2_hiera_l.yaml"),
])
def test_the_configuration_follows_the_checkpoints_name(name, config):
    assert sam2.config_name(Path(name)) == config


def test_bad_checkpoints_are_one_line(tmp_path):
    if not sam2.available():
        with pytest.raises(InputError, match=r"pip install 's3o-warp\[sam2\]'"):
            sam2.check(tmp_path / "sam2.1_hiera_tiny.pt")
        return
    with pytest.raises(InputError, match="needs --checkpoint PATH"):
        sam2.check(None)
    with pytest.raises(InputError, match="no such file"):
        sam2.check(tmp_path / "sam2.1_hiera_tiny.pt")
    (tmp_path / "weights.pt").write_bytes(b"")
    with pytest.raises(InputError, match="not a SAM 2 checkpoint name"):
        sam2.check(tmp_path / "weights.pt")


def test_a_model_without_weights_runs_the_video_path(tmp_path):
    if not sam2.available():
        pytest.skip("the sam2 package is not installed (pip install 's3o-warp[sam2]'): its video path is not run")
    import torch

    torch.manual_seed(0)
    # the tiny model at 256 px instead of 1024, random weights: the path, not the masks, is under test
    from sam2.build_sam import build_sam2_video_predictor

    predictor = build_sam2_video_predictor("configs/sam2.1/sam2.1_hiera_t.yaml", None, device="cpu",
                                           hydra_overrides_extra=["++model.image_size=256"])
    images, truth = scene(frames=3)
    files = []
    for k, im in enumerate(images):
        files.append(tmp_path / f"f{k}.png")
        cv2.imwrite(str(files[-1]), cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
    masks = sam2.propagate(predictor, files, {1: tuple(int(v) for v in box_of(truth[1]))})
    assert sorted(masks) == [0, 1, 2]
    assert all(m.shape == truth[0].shape and m.dtype == bool for m in masks.values())
