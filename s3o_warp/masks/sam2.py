"""The optional stronger segmenter: SAM 2's video predictor (the ``sam2`` package, ``pip install s3o-warp[sam2]``)
with weights the user downloaded once. The box prompts its frame; the predictor carries the mask forward and
backward through the video. Nothing is ever downloaded here.

The model's configuration follows the checkpoint's file name as Meta publishes it (``sam2.1_hiera_tiny.pt``,
``sam2_hiera_large.pt``, ...; :data:`CONFIGS`).
"""

from __future__ import annotations

import logging
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import torch

from s3o_warp.errors import InputError
from s3o_warp.masks.grabcut import LOST_FRACTION, Box, ObjectLost

log = logging.getLogger(__name__)

CONFIGS = {"tiny": "t", "small": "s", "base_plus": "b+", "large": "l"}
"""Checkpoint name part -> the ``sam2`` package's configuration suffix (``configs/sam2.1/sam2.1_hiera_<s>.yaml``)."""

_NAME = re.compile(r"^(sam2(?:\.1)?)_hiera_(tiny|small|base_plus|large)$")

DOWNLOAD = "https://github.com/facebookresearch/sam2#download-checkpoints"
"""Where the README sends users for the weights."""


def available() -> bool:
    """Whether the ``sam2`` package can be imported."""
    try:
        import sam2  # noqa: F401
    except ImportError:
        return False
    return True


def config_name(checkpoint: Path) -> str:
    """The ``sam2`` package's model configuration for a checkpoint file, from its name; InputError otherwise."""
    m = _NAME.match(checkpoint.stem)
    if not m:
        raise InputError(
            f"--checkpoint {checkpoint}: not a SAM 2 checkpoint name (sam2.1_hiera_tiny.pt, _small, _base_plus, "
            f"_large, or sam2_hiera_*.pt); keep the file's name as downloaded from {DOWNLOAD}"
        )
    version, size = m.groups()
    return f"configs/{version}/{version}_hiera_{CONFIGS[size]}.yaml"


def check(checkpoint: Path | None) -> None:
    """InputError when the ``sam2`` package is missing or the checkpoint is not given, not a file or misnamed."""
    if not available():
        raise InputError("--segmenter sam2 needs the sam2 package: pip install 's3o-warp[sam2]' (or use the default "
                         "segmenter)")
    if checkpoint is None:
        raise InputError(f"--segmenter sam2 needs --checkpoint PATH, SAM 2 weights downloaded once from {DOWNLOAD}")
    if not checkpoint.is_file():
        raise InputError(f"--checkpoint {checkpoint}: no such file; download SAM 2 weights from {DOWNLOAD}")
    config_name(checkpoint)


def build_predictor(config: str, checkpoint: Path | None, device: str = "cpu"):
    """SAM 2's video predictor; ``checkpoint`` None builds the model with random weights (the tests)."""
    from sam2.build_sam import build_sam2_video_predictor

    return build_sam2_video_predictor(config, str(checkpoint) if checkpoint else None, device=device)


def _device() -> str:
    return "cuda" if torch.cuda.is_available() else "cpu"


def propagate(predictor, files: list[Path], boxes: dict[int, Box]) -> dict[int, np.ndarray]:
    """SAM 2 prompted with each box on its frame and carried forward and backward through the video: ``{k: (H, W)
    bool}`` for every frame (a frame reached from several boxes takes the union of their masks).

    Args:
        predictor: from :func:`build_predictor`.
        files: the T frame files, in order.
        boxes: ``{frame: (x0, y0, x1, y1)}`` inclusive frame pixels.
    """
    masks: dict[int, np.ndarray] = {}
    with tempfile.TemporaryDirectory(prefix="s3o-sam2-") as tmp:
        # SAM 2 reads a folder of JPEG frames named by their index
        for k, f in enumerate(files):
            img = cv2.imread(str(f), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
            cv2.imwrite(str(Path(tmp) / f"{k:05d}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        with torch.inference_mode():
            state = predictor.init_state(video_path=tmp)
            for k, (x0, y0, x1, y1) in sorted(boxes.items()):
                predictor.add_new_points_or_box(state, frame_idx=k, obj_id=1,
                                                box=np.array([x0, y0, x1 + 1, y1 + 1], np.float32))
            for reverse in (False, True):
                for k, _, logits in predictor.propagate_in_video(state, reverse=reverse):
                    m = (logits[0, 0] > 0.0).cpu().numpy()
                    masks[k] = masks[k] | m if k in masks else m
    return masks


def segment_video(files: list[Path], boxes: dict[int, Box], checkpoint: Path) -> Iterator[tuple[int, np.ndarray]]:
    """Masks of every frame, as ``(k, (H, W) bool)`` pairs in order, from SAM 2 with the weights ``checkpoint``
    (:func:`propagate`).

    Raises:
        ObjectLost: the first frame, going out from each box, whose mask is under
            :data:`s3o_warp.masks.grabcut.LOST_FRACTION` of its nearest box frame's (the same rule as the default
            segmenter's).
    """
    masks = propagate(build_predictor(config_name(checkpoint), checkpoint, _device()), files, boxes)
    anchors = sorted(boxes)
    for k in sorted(range(len(files)), key=lambda k: min(abs(k - a) for a in anchors)):
        a = min(anchors, key=lambda a: abs(k - a))
        area, anchor_area = int(masks[k].sum()), int(masks[a].sum())
        if area == 0 or area < LOST_FRACTION * anchor_area:
            raise ObjectLost(k, a, area, anchor_area)
    for k in range(len(files)):
        yield k, masks[k]
