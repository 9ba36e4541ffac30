"""Reading masks: one mask file to a boolean foreground, and the clean-up the fit applies to it.

Masks: a palette PNG gives object ids (``DataConfig.object_id`` selects one; None = every non-zero
id); a single-channel label image with ``object_id`` set gives the pixels carrying that id; any other
mask is foreground where value (for colour masks: the brightest channel) > ``DataConfig.mask_threshold``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from s3o_warp.config import DataConfig
from s3o_warp.errors import InputError

BLOB_GAP = 0.05
"""``data.largest_blob``: fragments within this fraction of the largest blob's bbox diagonal belong to the object
(thin legs break off a mask by a pixel or two)."""


def read_mask(path: Path, object_id: int | None = None, threshold: int = DataConfig.mask_threshold) -> np.ndarray:
    """Boolean (H, W) foreground of one mask file; see the module docstring for the rules (``object_id`` and
    ``threshold``: ``DataConfig.object_id`` and ``mask_threshold``)."""
    try:
        with Image.open(path) as im:
            im.load()
            mode = im.mode
            if mode == "P":
                arr = np.array(im)
            elif mode in ("1", "L", "I", "I;16", "F"):
                arr = np.array(im)
            else:  # RGB(A), LA, CMYK...: a coloured mask is foreground where any channel is bright
                arr = np.array(im.convert("RGB")).max(axis=-1)
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise InputError(
            f"{path}: cannot read this mask ({exc.__class__.__name__}); replace or remove the file"
        ) from None
    if mode == "P":
        if object_id is None:
            return arr != 0
        fg = arr == object_id
        if not fg.any():
            ids = ", ".join(str(int(i)) for i in np.unique(arr))
            raise InputError(
                f"{path}: palette mask has no pixel with object id {object_id} (ids present: {ids}); "
                "set data.object_id (--object-id) to the object's id, or fix or remove this frame"
            )
        return fg
    if mode == "1":
        return arr.astype(bool)
    if object_id is not None and mode in ("L", "I", "I;16"):
        # a single-channel label image: the object's pixels carry its id
        fg = arr == object_id
        if not fg.any():
            raise InputError(
                f"{path}: label mask has no pixel with object id {object_id}; "
                "set data.object_id to the object's value, or None for binary masks"
            )
        return fg
    return arr > threshold


def clean_mask(mask: np.ndarray, cfg) -> np.ndarray:
    """The mask as the fit uses it: with ``data.largest_blob``, the largest blob and the fragments near it.

    Thin parts (a leg, a tail tip) often break off a few pixels from the body in a mask; they belong to
    the object and are kept when they lie within :data:`BLOB_GAP` x the largest blob's bbox diagonal of
    it. Blobs farther away (another object, noise) are dropped.
    """
    if not getattr(cfg, "largest_blob", False) or not mask.any():
        return mask
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 2:
        return mask
    best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    w, h = stats[best, cv2.CC_STAT_WIDTH], stats[best, cv2.CC_STAT_HEIGHT]
    r = max(1, int(round(BLOB_GAP * float(np.hypot(w, h)))))
    near = cv2.dilate((labels == best).astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    keep = np.unique(labels[(near > 0) & (labels > 0)])
    return np.isin(labels, keep)


def largest_component(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected foreground component of a boolean ``(H, W)`` mask (all False if empty)."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(mask, dtype=bool)
    best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return labels == best
