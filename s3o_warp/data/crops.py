"""Square crops of a frame around its mask box: boxes, the crop <-> frame transform, resampling, point and
intrinsics mapping.

Pixel convention everywhere (OpenCV's): the centre of pixel (column c, row r) is at (c, r), and an
image of width W spans [-0.5, W - 0.5]. A :class:`Crop` keeps the exact 3x3 similarity
``crop_to_frame`` mapping homogeneous crop pixel coordinates to full-frame pixel coordinates, so
``K_frame = crop_to_frame @ K_crop`` (:func:`intrinsics_crop_to_frame`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch

CROP_BACKGROUND = (0, 0, 0)
"""RGB colour given to crop pixels that fall outside the frame (masks get 0 there)."""


def mask_bbox(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """Inclusive pixel bounding box ``(x0, y0, x1, y1)`` of a boolean ``(H, W)`` mask; None when empty.

    Concretely, foreground pixel centres span columns x0..x1 and rows y0..y1, so the box's edges in
    the pixel-centre convention are at x0 - 0.5 and x1 + 0.5.
    """
    cols = np.flatnonzero(mask.any(axis=0))
    if cols.size == 0:
        return None
    rows = np.flatnonzero(mask.any(axis=1))
    return int(cols[0]), int(rows[0]), int(cols[-1]), int(rows[-1])


def crop_transform(bbox: tuple[int, int, int, int], crop_size: int, crop_scale: float) -> np.ndarray:
    """``crop_to_frame`` (3, 3) float64 for the square crop around an inclusive pixel box.

    The square is centred on the box centre ((x0 + x1) / 2, (y0 + y1) / 2) with side
    ``crop_scale * max(x1 - x0 + 1, y1 - y0 + 1)`` frame pixels; its edges map to the crop image's
    edges -0.5 and crop_size - 0.5. With a = side / crop_size (frame pixels per crop pixel), crop
    pixel (c, r) sits at frame point (a (c + 0.5) + left, a (r + 0.5) + top).
    """
    x0, y0, x1, y1 = bbox
    side = crop_scale * max(x1 - x0 + 1, y1 - y0 + 1)
    a = side / crop_size
    left = 0.5 * (x0 + x1) - 0.5 * side
    top = 0.5 * (y0 + y1) - 0.5 * side
    return np.array([[a, 0.0, left + 0.5 * a], [0.0, a, top + 0.5 * a], [0.0, 0.0, 1.0]])


def map_points(points: Any, transform: Any) -> Any:
    """Apply a 3x3 pixel transform to points ``(..., 2)`` (numpy or torch, same type back).

    Args:
        points: ``(..., 2)`` pixel coordinates (x = column, y = row), pixel-centre convention.
        transform: ``(3, 3)`` or, for per-frame points, ``(T, 3, 3)`` broadcast against
            ``points (T, N, 2)``; e.g. ``Crop.crop_to_frame`` maps crop pixels to frame pixels.

    Returns:
        ``(..., 2)`` mapped points, dtype of ``points`` (numpy) or promoted (torch).
    """
    if isinstance(points, torch.Tensor):
        tr = torch.as_tensor(transform, dtype=points.dtype, device=points.device)
        lin, off = tr[..., :2, :2], tr[..., :2, 2]
        if tr.dim() == 3:
            return torch.einsum("tij,tnj->tni", lin, points) + off[:, None, :]
        return points @ lin.T + off
    pts = np.asarray(points)
    tr = np.asarray(transform, dtype=np.float64)
    lin, off = tr[..., :2, :2], tr[..., :2, 2]
    if tr.ndim == 3:
        out = np.einsum("tij,tnj->tni", lin, pts) + off[:, None, :]
    else:
        out = pts @ lin.T + off
    return out.astype(pts.dtype) if np.issubdtype(pts.dtype, np.floating) else out


def intrinsics_crop_to_frame(K_crop: Any, crop_to_frame: Any) -> Any:
    """``K_frame = crop_to_frame @ K_crop``: pinhole intrinsics ``(..., 3, 3)`` from crop to frame pixels.

    Exact because a crop transform is affine (last row 0, 0, 1): projecting with K_frame equals
    projecting with K_crop and mapping the pixel with crop_to_frame. numpy or torch in, same out.
    """
    return _as_like(crop_to_frame, K_crop) @ K_crop


def intrinsics_frame_to_crop(K_frame: Any, frame_to_crop: Any) -> Any:
    """``K_crop = frame_to_crop @ K_frame``: the inverse of :func:`intrinsics_crop_to_frame`."""
    return _as_like(frame_to_crop, K_frame) @ K_frame


def _as_like(m: Any, like: Any) -> Any:
    if isinstance(like, torch.Tensor):
        return torch.as_tensor(m, dtype=like.dtype, device=like.device)
    return np.asarray(m, dtype=np.result_type(np.asarray(like).dtype, np.float64))


def warp_similarity(
    image: np.ndarray,
    out_to_in: np.ndarray,
    out_size: tuple[int, int],
    border_value: float | tuple[float, ...] = 0,
    interpolation: int = cv2.INTER_LINEAR,
) -> np.ndarray:
    """Resample ``image`` on an output grid given by a scale + translation ``out_to_in`` (3, 3).

    Output pixel (c, r) takes the (bilinear) value at input point ``out_to_in @ (c, r, 1)``
    (pixel-centre convention, exact up to OpenCV's 1/32-pixel interpolation table); outside the
    input it gets ``border_value``. When the output is more than 2x coarser than the input, the
    input is first reduced with ``cv2.pyrDown`` (Gaussian, centre-preserving: input pixel x of a
    pyrDown level is pixel 2x of the level below) so the result is not aliased.

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` uint8 or float32.
        out_to_in: ``(3, 3)`` similarity without rotation: ``[[a, 0, tx], [0, a, ty], [0, 0, 1]]``.
        out_size: ``(height, width)`` of the output.
        border_value: value (or per-channel values) outside the input.
        interpolation: OpenCV flag (``cv2.INTER_LINEAR`` or ``cv2.INTER_NEAREST``).

    Returns:
        ``(height, width[, C])`` array, dtype of ``image``.
    """
    m = np.array(out_to_in, dtype=np.float64)
    src = image
    if interpolation != cv2.INTER_NEAREST:
        while m[0, 0] >= 2.0 and min(src.shape[:2]) >= 4:
            src = cv2.pyrDown(src)
            # level-k pixel x sits at level-(k-1) pixel 2x, so in level-k pixels the point is p / 2
            m = np.diag([0.5, 0.5, 1.0]) @ m
    in_to_out = np.linalg.inv(m)[:2]
    bv = border_value if isinstance(border_value, (tuple, list)) else (border_value,) * 4
    return cv2.warpAffine(
        src,
        in_to_out,
        (int(out_size[1]), int(out_size[0])),
        flags=interpolation,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=tuple(float(v) for v in bv),
    )


@dataclass
class Crop:
    """One frame's square crop at the working resolution S = ``DataConfig.crop_size``.

    Attributes:
        image: ``(S, S, 3) uint8`` RGB crop; pixels outside the frame are :data:`CROP_BACKGROUND`.
        mask: ``(S, S) bool`` foreground crop; False outside the frame.
        crop_to_frame: ``(3, 3) float64``; frame pixel = crop_to_frame @ (c, r, 1) for crop pixel (c, r).
        frame_to_crop: ``(3, 3) float64`` inverse of crop_to_frame.
        bbox: inclusive frame-pixel mask box ``(x0, y0, x1, y1)`` the crop was made from.
    """

    image: np.ndarray
    mask: np.ndarray
    crop_to_frame: np.ndarray
    frame_to_crop: np.ndarray
    bbox: tuple[int, int, int, int]


def crop_frame(
    image: np.ndarray,
    mask: np.ndarray,
    crop_size: int,
    crop_scale: float,
    background: tuple[int, int, int] = CROP_BACKGROUND,
    bbox: tuple[int, int, int, int] | None = None,
) -> Crop:
    """Square crop of a frame around its mask box, resized to ``crop_size x crop_size``.

    Args:
        image: ``(H, W, 3)`` uint8 RGB (or float32) full frame.
        mask: ``(H, W)`` bool foreground; must not be empty.
        crop_size: S, output side in pixels.
        crop_scale: square side as a multiple of the mask box's longer side (see :func:`crop_transform`).
        background: RGB fill where the square leaves the frame.
        bbox: the mask's box if already known (saves a pass over the mask).

    Returns:
        :class:`Crop` with the image (bilinear, anti-aliased when shrinking), the mask (resampled as
        0/255 and thresholded at half) and the exact crop <-> frame transforms.

    Raises:
        ValueError: empty mask, or image and mask sizes differ.
    """
    if image.shape[:2] != mask.shape[:2]:
        raise ValueError(f"crop_frame(): image {image.shape[:2]} and mask {mask.shape[:2]} differ in size")
    if bbox is None:
        bbox = mask_bbox(mask)
        if bbox is None:
            raise ValueError("crop_frame(): the mask is empty")
    c2f = crop_transform(bbox, crop_size, crop_scale)
    img = warp_similarity(image, c2f, (crop_size, crop_size), tuple(background))
    msk = warp_similarity(mask.astype(np.uint8) * 255, c2f, (crop_size, crop_size), 0) > 127
    return Crop(image=img, mask=msk, crop_to_frame=c2f, frame_to_crop=np.linalg.inv(c2f), bbox=bbox)

