"""Optical flow between consecutive crops (OpenCV DIS), with forward-backward confidence, cached on disk.

What is computed, for each pair of frames (t, t+1) with crops A_t, A_{t+1} (``crop_to_frame``):

1. A *flow canvas* covering both crop squares (their union, clipped to the frame) is resampled from
   both full frames at a common scale g = max(1, min(a_t, a_{t+1})) frame pixels per canvas pixel
   (a = crop side / crop_size), so the canvas is never finer than the frame nor coarser than either
   crop; DIS runs on the two grey canvases, forward (t -> t+1) and backward.
2. The canvas flows are expressed in crop pixels. Concretely, ``flow_fwd[r, c] = (dx, dy)`` means
   the scene point at crop-t pixel (c, r) is seen at crop-(t+1) pixel (c + dx, r + dy), i.e.
   ``f(p) = A_{t+1}^-1 (x + F(x)) - p`` with x = A_t p and F the frame flow. Each frame keeps its
   own crop, so a static background generally has non-zero crop flow; this is the displacement a
   renderer gives when it projects vertices with each frame's own crop intrinsics.
   ``flow_bwd`` is the same from crop t+1 to crop t.
3. Confidence ``conf_fwd(p) = exp(-|f(p) + b(p + f(p))|^2 / (2 sigma^2))`` (sigma =
   :data:`FLOW_FB_SIGMA` in crop-t pixels), evaluated exactly on the canvas (the error is the
   canvas round-trip error scaled to crop-t pixels), and 0 where p or p + f(p) falls outside the
   frame. ``conf_bwd`` likewise on crop t+1.

Each pair is one memory-mappable ``<cache_dir>/flow_<key>.npy`` of shape (S, S, 6) float32
(channels: fwd dx, fwd dy, bwd dx, bwd dy, conf_fwd, conf_bwd), keyed on a SHA-256 of both frames'
content, both masks, the crop and flow settings and the OpenCV version; written atomically
(:mod:`s3o_warp.data.io`). A second :func:`compute_flow` over the same content only checks headers.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm.auto import tqdm

from s3o_warp.config import DataConfig
from s3o_warp.data.crops import warp_similarity
from s3o_warp.data.io import write_stream
from s3o_warp.data.sequence import Sequence, check_data_config
from s3o_warp import interrupt
from s3o_warp.errors import ConfigError, InputError

log = logging.getLogger(__name__)

FLOW_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}
"""``DataConfig.flow_preset`` names and their OpenCV DIS presets."""

FLOW_FORMAT_VERSION = 1
"""Bumped whenever what is stored in a flow cache file changes (old files are then ignored)."""

FLOW_FINEST_SCALE = 0
"""DIS's finest pyramid level: 0 = the flow canvas's full resolution (the medium preset's own is 1, half; fast and
ultrafast stop at 2, a quarter). At the preset's level the synthetic renders' flow is 0.87-0.90 of the true motion,
at 0 0.96-0.97 (``scripts/bench_flow.py``)."""

FLOW_FB_SIGMA = 1.0
"""Forward-backward consistency: confidence = exp(-|f + b(x + f)|^2 / (2 sigma^2)), sigma in crop pixels."""

_CHANNELS = 6
_MIN_CANVAS = 32


@dataclass
class FlowPair:
    """Flow between crops t and t+1, crop pixels (S = ``DataConfig.crop_size``); read-only arrays.

    Attributes:
        flow_fwd: ``(S, S, 2) float32`` (dx, dy): crop-t pixel (c, r) moves to crop-(t+1) pixel
            (c + dx, r + dy).
        flow_bwd: ``(S, S, 2) float32``: crop-(t+1) pixel (c, r) comes from crop-t pixel (c + dx, r + dy).
        conf_fwd: ``(S, S) float32`` in [0, 1], forward-backward consistency of flow_fwd.
        conf_bwd: ``(S, S) float32`` in [0, 1], forward-backward consistency of flow_bwd.
    """

    flow_fwd: np.ndarray
    flow_bwd: np.ndarray
    conf_fwd: np.ndarray
    conf_bwd: np.ndarray

    @classmethod
    def from_array(cls, arr: np.ndarray) -> FlowPair:
        """Views into one stored ``(S, S, 6)`` array."""
        return cls(arr[..., 0:2], arr[..., 2:4], arr[..., 4], arr[..., 5])


@dataclass
class FlowCache:
    """On-disk flow for every consecutive pair of a sequence; pairs are memory-mapped on access.

    Attributes:
        cache_dir: folder holding the ``flow_<key>.npy`` files.
        files: T - 1 files; ``files[t]`` holds pair (t, t+1).
        crop_size: S.
        crop_to_frame: ``(T, 3, 3) float64`` crop -> frame transforms the flows refer to.
        computed: pairs computed by the call that made this object.
        hits: pairs found in the cache by that call.
    """

    cache_dir: Path
    files: list[Path]
    crop_size: int
    crop_to_frame: np.ndarray
    computed: int = 0
    hits: int = 0

    def __len__(self) -> int:
        return len(self.files)

    def pair(self, t: int) -> FlowPair:
        """Pair (t, t+1), memory-mapped (nothing else is loaded)."""
        path = self.files[t]
        try:
            arr = np.load(path, mmap_mode="r")
        except (OSError, ValueError) as exc:
            raise InputError(f"{path}: cannot read this flow cache file ({exc}); delete it to recompute") from None
        return FlowPair.from_array(arr)

    def __getitem__(self, t: int) -> FlowPair:
        return self.pair(t)

    def __iter__(self) -> Iterator[FlowPair]:
        for t in range(len(self)):
            yield self.pair(t)


def make_dis(preset: str, finest_scale: int | None = None) -> cv2.DISOpticalFlow:
    """An OpenCV DIS optical-flow object for ``DataConfig.flow_preset`` and a finest pyramid level (None: the
    preset's; the fit uses :data:`FLOW_FINEST_SCALE`)."""
    if preset not in FLOW_PRESETS:
        raise ConfigError(f"data.flow_preset must be one of {', '.join(FLOW_PRESETS)}, got {preset!r}")
    dis = cv2.DISOpticalFlow_create(FLOW_PRESETS[preset])
    if finest_scale is not None:
        dis.setFinestScale(int(finest_scale))
    return dis


def flow_canvas(
    crop_to_frame_a: np.ndarray, crop_to_frame_b: np.ndarray, frame_size: tuple[int, int], crop_size: int
) -> tuple[np.ndarray, tuple[int, int]]:
    """The common region on which the flow of a pair is computed, at the finer of the frame and the coarser crop
    (see the module docstring).

    Returns:
        ``canvas_to_frame`` (3, 3) float64 (scale g, translation) and the canvas ``(height, width)``.
    """
    H, W = frame_size
    boxes = []
    for m in (crop_to_frame_a, crop_to_frame_b):
        a = m[0, 0]
        left, top = m[0, 2] - 0.5 * a, m[1, 2] - 0.5 * a
        boxes.append((left, top, left + a * crop_size, top + a * crop_size))
    left = max(min(b[0] for b in boxes), -0.5)
    top = max(min(b[1] for b in boxes), -0.5)
    right = min(max(b[2] for b in boxes), W - 0.5)
    bottom = min(max(b[3] for b in boxes), H - 0.5)
    g = max(1.0, min(crop_to_frame_a[0, 0], crop_to_frame_b[0, 0]))
    wc = max(math.ceil((right - left) / g - 1e-9), _MIN_CANVAS)
    hc = max(math.ceil((bottom - top) / g - 1e-9), _MIN_CANVAS)
    canvas_to_frame = np.array([[g, 0.0, left + 0.5 * g], [0.0, g, top + 0.5 * g], [0.0, 0.0, 1.0]])
    return canvas_to_frame, (hc, wc)


def _to_crop(
    flow_ab: np.ndarray,
    flow_ba: np.ndarray,
    canvas_to_frame: np.ndarray,
    c2f_a: np.ndarray,
    c2f_b: np.ndarray,
    frame_size: tuple[int, int],
    crop_size: int,
    sigma: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Canvas flow a -> b expressed on crop a's grid, in crop-a -> crop-b pixels, and its confidence."""
    H, W = frame_size
    S = crop_size
    g = canvas_to_frame[0, 0]
    rc, cc = np.mgrid[0:S, 0:S].astype(np.float64)
    p = np.stack([cc, rc], axis=-1)  # (S, S, 2) crop-a pixel centres (x, y)
    x = p * c2f_a[0, 0] + c2f_a[:2, 2]  # frame points
    u = (x - canvas_to_frame[:2, 2]) / g  # canvas points
    ux, uy = u[..., 0].astype(np.float32), u[..., 1].astype(np.float32)
    fu = cv2.remap(flow_ab, ux, uy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    u2 = u + fu
    bu = cv2.remap(
        flow_ba, u2[..., 0].astype(np.float32), u2[..., 1].astype(np.float32), cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    ).astype(np.float64)
    x2 = u2 * g + canvas_to_frame[:2, 2]  # target frame points
    q = (x2 - c2f_b[:2, 2]) / c2f_b[0, 0]  # target crop-b pixels
    flow = q - p
    err = (fu + bu) * (g / c2f_a[0, 0])  # canvas round-trip error in crop-a pixels
    hc, wc = flow_ab.shape[:2]

    def inside(pt: np.ndarray, w: float, h: float) -> np.ndarray:
        return (pt[..., 0] >= -0.5) & (pt[..., 0] <= w - 0.5) & (pt[..., 1] >= -0.5) & (pt[..., 1] <= h - 0.5)

    valid = inside(x, W, H) & inside(x2, W, H) & inside(u, wc, hc) & inside(u2, wc, hc)
    conf = np.exp(-np.sum(err**2, axis=-1) / (2.0 * sigma**2)) * valid
    return flow.astype(np.float32), conf.astype(np.float32)


def pair_flow(
    image_a: np.ndarray,
    image_b: np.ndarray,
    crop_to_frame_a: np.ndarray,
    crop_to_frame_b: np.ndarray,
    crop_size: int,
    sigma: float,
    dis: cv2.DISOpticalFlow,
) -> np.ndarray:
    """Forward/backward crop flow and confidences of one frame pair (no caching).

    Args:
        image_a, image_b: ``(H, W, 3) uint8`` RGB full frames t and t+1.
        crop_to_frame_a, crop_to_frame_b: ``(3, 3)`` crop transforms of the two frames.
        crop_size: S.
        sigma: forward-backward sigma in crop pixels.
        dis: from :func:`make_dis`.

    Returns:
        ``(S, S, 6) float32``: fwd dx, fwd dy, bwd dx, bwd dy, conf_fwd, conf_bwd (see :class:`FlowPair`).
    """
    size = image_a.shape[:2]
    g2f, (hc, wc) = flow_canvas(crop_to_frame_a, crop_to_frame_b, size, crop_size)
    ca = warp_similarity(cv2.cvtColor(image_a, cv2.COLOR_RGB2GRAY), g2f, (hc, wc), 0)
    cb = warp_similarity(cv2.cvtColor(image_b, cv2.COLOR_RGB2GRAY), g2f, (hc, wc), 0)
    fwd = dis.calc(ca, cb, None)
    bwd = dis.calc(cb, ca, None)
    f_ab, c_ab = _to_crop(fwd, bwd, g2f, crop_to_frame_a, crop_to_frame_b, size, crop_size, sigma)
    f_ba, c_ba = _to_crop(bwd, fwd, g2f, crop_to_frame_b, crop_to_frame_a, size, crop_size, sigma)
    return np.concatenate([f_ab, f_ba, c_ab[..., None], c_ba[..., None]], axis=-1)


def pair_payload(seq: Sequence, t: int, u: int, cfg: DataConfig) -> dict:
    """What the flow of frames (t, u) depends on: frame and mask content, boxes, settings, versions."""
    return {
        "format": FLOW_FORMAT_VERSION,
        "opencv": cv2.__version__,
        "frames": [seq.frame_digest(t), seq.frame_digest(u)],
        "masks": [seq.mask_digests[t], seq.mask_digests[u]],
        "bboxes": [[int(v) for v in seq.bboxes[t]], [int(v) for v in seq.bboxes[u]]],
        "size": list(seq.size),
        "crop_size": seq.cfg.crop_size,
        "crop_scale": float(seq.cfg.crop_scale),
        "flow_preset": cfg.flow_preset,
        "flow_fb_sigma": float(FLOW_FB_SIGMA),
        "flow_finest_scale": int(FLOW_FINEST_SCALE),
    }


def pair_key(seq: Sequence, t: int, cfg: DataConfig) -> str:
    """SHA-256 hex key of pair (t, t+1) (:func:`pair_payload`)."""
    payload = pair_payload(seq, t, t + 1, cfg)
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def _is_valid_file(path: Path, crop_size: int) -> bool:
    try:
        arr = np.load(path, mmap_mode="r")
    except (OSError, ValueError):
        return False
    return arr.shape == (crop_size, crop_size, _CHANNELS) and arr.dtype == np.float32


def compute_flow(seq: Sequence, cache_dir: str | Path, cfg: DataConfig | None = None) -> FlowCache:
    """Flow for every pair (t, t+1) of ``seq``, computed once and cached under ``cache_dir``.

    Pairs already in the cache (same content and settings) are not recomputed; missing ones are
    computed one at a time (two decoded frames in memory) with a tqdm bar; a stop request
    (:mod:`s3o_warp.interrupt`) ends it between pairs, the pairs done so far cached. ``cache_dir`` is only
    created when a pair has to be written.

    Args:
        seq: from :func:`s3o_warp.data.sequence.open_sequence`; its crops define the crop coordinates.
        cache_dir: e.g. ``<run>/cache``.
        cfg: flow settings (``flow_preset``); defaults
            to ``seq.cfg``. Its crop settings must equal the sequence's.

    Returns:
        :class:`FlowCache` with T - 1 pairs.

    Raises:
        ConfigError: bad flow setting, or crop settings that differ from the sequence's.
        InputError: a frame that cannot be decoded (named).
    """
    cfg = cfg or seq.cfg
    check_data_config(cfg)
    if (cfg.crop_size, cfg.crop_scale) != (seq.cfg.crop_size, seq.cfg.crop_scale):
        raise ConfigError(
            f"data.crop_size/crop_scale ({cfg.crop_size}, {cfg.crop_scale}) differ from the sequence's "
            f"({seq.cfg.crop_size}, {seq.cfg.crop_scale}); open the sequence with the same DataConfig"
        )
    cache_dir = Path(cache_dir)
    S = cfg.crop_size
    c2f = seq.crop_to_frame  # the crop settings are the sequence's (checked above)
    files = [cache_dir / f"flow_{pair_key(seq, t, cfg)[:40]}.npy" for t in range(seq.num_frames - 1)]
    todo = [t for t, f in enumerate(files) if not (f.is_file() and _is_valid_file(f, S))]
    dis = make_dis(cfg.flow_preset, FLOW_FINEST_SCALE) if todo else None
    for k, t in enumerate(tqdm(todo, desc=f"{seq.name}: optical flow", unit="pair", leave=False, disable=None)):
        interrupt.check(f"the optical flow ({len(files) - len(todo) + k} of {len(files)} pairs cached)")
        arr = pair_flow(seq.image(t), seq.image(t + 1), c2f[t], c2f[t + 1], S, FLOW_FB_SIGMA, dis)
        cache_dir.mkdir(parents=True, exist_ok=True)
        write_stream(files[t], lambda f: np.save(f, arr))
    hits = len(files) - len(todo)
    log.info(
        "%s: optical flow for %d pairs (%d computed, %d cached) in %s", seq.name, len(files), len(todo), hits, cache_dir
    )
    return FlowCache(cache_dir=cache_dir, files=files, crop_size=S, crop_to_frame=c2f, computed=len(todo), hits=hits)
