"""Optical flow between frames far apart (gaps 1, 2, 4, ..., 32): direct DIS, composed chains and a per-pixel pick
of the more reliable, with forward-backward confidences, cached on disk like the consecutive flow.

Same crop coordinates and channel layout as :mod:`s3o_warp.data.flow`: for a pair (t, t + g),
``flow_fwd[r, c] = (dx, dy)`` sends crop-t pixel (c, r) to crop-(t + g) pixel (c + dx, r + dy), ``flow_bwd`` the same
from crop t + g back to crop t, each with a confidence in [0, 1].

For a gap g > 1:

1. *composed*: the kept flows of two shorter gaps a + b = g (with the default gaps, g/2 + g/2; gap 1 is today's
   consecutive flow) chained, ``f(p) = f_a(p) + f_b(p + f_a(p))`` (bilinear), the confidence the product of the
   hops' confidences, ``c_a(p) c_b(p + f_a(p))``, so each hop keeps its own forward-backward check; 0 where the
   first hop leaves the middle crop (the flow there is not stored).
2. *direct* (gaps up to :data:`DIRECT_MAX_GAP`): DIS on the pair as for a consecutive pair
   (:func:`s3o_warp.data.flow.pair_flow`), but with the background blanked (:data:`DIRECT_MASK_MARGIN`) on a
   canvas that covers the two mask boxes (:func:`object_canvas`), its confidence the pair's forward-backward
   check (0 on blanked pixels); per pixel and direction, the more confident of direct and composed is kept
   (:func:`pick_pairs`).

Direct DIS fails where the appearance changes between the two frames (the animal turns, a leg swings through) and
its failures are often forward-backward consistent; a chain drifts by its hops' small errors and breaks where one
hop is occluded. Measured against the true flow of the synthetic sequences (``scripts/bench_long_flow.py``), the
pick beats both at gap 2 and direct DIS stops helping from gap 4 on, so longer gaps are chains of picked flows.

Each pair (t, g > 1) is one memory-mappable ``<cache_dir>/lflow_<key>.npy`` of shape (S, S, 6) float32 (the
channels of :class:`~s3o_warp.data.flow.FlowPair`), keyed on a SHA-256 of the keys of the two hops it is composed
of and, where direct DIS is used, the pair's content and settings (so a change to any frame between t and t + g
changes it); written atomically (:mod:`s3o_warp.data.io`). Gap 1 is :func:`s3o_warp.data.flow.compute_flow`'s own
cache.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm.auto import tqdm

from s3o_warp import interrupt
from s3o_warp.config import DataConfig
from s3o_warp.data.crops import warp_similarity
from s3o_warp.data.flow import (
    _MIN_CANVAS,
    FLOW_FB_SIGMA,
    FLOW_FINEST_SCALE,
    FlowPair,
    _is_valid_file,
    _to_crop,
    compute_flow,
    make_dis,
    pair_key,
    pair_payload,
)
from s3o_warp.data.io import write_stream
from s3o_warp.data.sequence import Sequence
from s3o_warp.errors import ConfigError, InputError

log = logging.getLogger(__name__)

LONG_FLOW_GAPS = (1, 2, 4, 8, 16, 32)
"""The default gaps (frames); those shorter than the clip are used. Each gap > 1 is composed of two shorter ones."""

LONG_FLOW_FORMAT_VERSION = 1
"""Bumped whenever what is stored in a long-flow cache file changes (old files are then ignored)."""

DIRECT_MAX_GAP = 2
"""Gaps up to this one pick per pixel between direct DIS and the chain; longer gaps are the chain alone. Measured on
the synthetic orbits (``scripts/bench_long_flow.py``): at gap 2 the pick's mean end-point error is a third of the
chain's and below direct DIS's; from gap 4 on, direct DIS is no better than the chain where it is confident (gap 8:
2.9 against 1.05 crop pixels on fox120), so taking it there makes the kept flow worse, and it would more than
double the time."""

DIRECT_MASK_MARGIN = 3
"""Direct DIS sees only the object: pixels farther than this (frame pixels) from the mask are set to black in both
frames. Over a long gap the background moves far more than the object a camera follows, and DIS's coarse levels
follow the background: on the synthetic Fox orbit the median end-point error at gap 8 falls from 14.2 to 1.0
crop pixels with the background blanked (``scripts/bench_long_flow.py``)."""


def default_gaps(num_frames: int) -> tuple[int, ...]:
    """:data:`LONG_FLOW_GAPS` shorter than a clip of ``num_frames`` frames."""
    return tuple(g for g in LONG_FLOW_GAPS if g < num_frames)


def hop_split(gaps) -> dict[int, tuple[int, int]]:
    """For each gap g > 1, the two shorter gaps (a, b), a + b = g, both in ``gaps``, whose kept flows are chained
    (a the largest such; with powers of two, g/2 + g/2).

    Raises:
        ConfigError: gap 1 missing, a gap under 1, or a gap that is not the sum of two shorter ones.
    """
    gs = sorted({int(g) for g in gaps})
    if not gs or gs[0] < 1 or gs[0] != 1:
        raise ConfigError(f"long-flow gaps must be whole numbers >= 1 and include 1, got {list(gaps)}")
    out = {}
    for g in gs[1:]:
        pairs = [(a, g - a) for a in gs if a < g and (g - a) in gs and a >= g - a]
        if not pairs:
            raise ConfigError(
                f"long-flow gap {g} is not the sum of two shorter gaps of {gs}; add them (e.g. powers of two)"
            )
        out[g] = max(pairs)
    return out


def _near_mask(mask: np.ndarray, margin: int) -> np.ndarray:
    """``(H, W) uint8`` 1 within ``margin`` pixels of ``mask``, else 0."""
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * margin + 1, 2 * margin + 1), np.uint8))


def object_only(image: np.ndarray, mask: np.ndarray, margin: int = DIRECT_MASK_MARGIN) -> np.ndarray:
    """Grey ``(H, W) uint8`` of the RGB ``image``, every pixel farther than ``margin`` pixels from ``mask`` set to 0."""
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) * _near_mask(mask, margin)


def object_canvas(
    bbox_a, bbox_b, crop_to_frame_a: np.ndarray, crop_to_frame_b: np.ndarray, frame_size: tuple[int, int],
    margin: int = DIRECT_MASK_MARGIN,
) -> tuple[np.ndarray, tuple[int, int]]:
    """The canvas of a direct pair: the union of the two mask boxes grown by ``margin`` (nothing else is left in
    :func:`object_only`'s pictures), at :func:`~s3o_warp.data.flow.flow_canvas`'s scale. Returns
    ``canvas_to_frame`` (3, 3) and ``(height, width)``."""
    H, W = frame_size
    left = max(min(bbox_a[0], bbox_b[0]) - margin - 0.5, -0.5)
    top = max(min(bbox_a[1], bbox_b[1]) - margin - 0.5, -0.5)
    right = min(max(bbox_a[2], bbox_b[2]) + margin + 0.5, W - 0.5)
    bottom = min(max(bbox_a[3], bbox_b[3]) + margin + 0.5, H - 0.5)
    g = max(1.0, min(crop_to_frame_a[0, 0], crop_to_frame_b[0, 0]))
    wc = max(math.ceil((right - left) / g - 1e-9), _MIN_CANVAS)
    hc = max(math.ceil((bottom - top) / g - 1e-9), _MIN_CANVAS)
    return np.array([[g, 0.0, left + 0.5 * g], [0.0, g, top + 0.5 * g], [0.0, 0.0, 1.0]]), (hc, wc)


def object_pair_flow(
    image_a: np.ndarray, image_b: np.ndarray, mask_a: np.ndarray, mask_b: np.ndarray, bbox_a, bbox_b,
    crop_to_frame_a: np.ndarray, crop_to_frame_b: np.ndarray, crop_size: int, dis: cv2.DISOpticalFlow,
) -> np.ndarray:
    """Direct DIS flow of one frame pair on the object only (:func:`object_only`, :func:`object_canvas`),
    ``(S, S, 6)`` as :func:`~s3o_warp.data.flow.pair_flow`; crop pixels off the canvas or blanked in their own frame
    get confidence 0.

    Args:
        image_a, image_b: ``(H, W, 3) uint8`` RGB frames; mask_a, mask_b: their ``(H, W)`` foregrounds;
        bbox_a, bbox_b: the masks' inclusive boxes ``(x0, y0, x1, y1)``; crop_to_frame_a, crop_to_frame_b: the
        crops' transforms; crop_size: S; dis: from :func:`~s3o_warp.data.flow.make_dis`.
    """
    size = image_a.shape[:2]
    g2f, (hc, wc) = object_canvas(bbox_a, bbox_b, crop_to_frame_a, crop_to_frame_b, size)
    ca = warp_similarity(object_only(image_a, mask_a), g2f, (hc, wc), 0)
    cb = warp_similarity(object_only(image_b, mask_b), g2f, (hc, wc), 0)
    fwd = dis.calc(ca, cb, None)
    bwd = dis.calc(cb, ca, None)
    f_ab, c_ab = _to_crop(fwd, bwd, g2f, crop_to_frame_a, crop_to_frame_b, size, crop_size, FLOW_FB_SIGMA)
    f_ba, c_ba = _to_crop(bwd, fwd, g2f, crop_to_frame_b, crop_to_frame_a, size, crop_size, FLOW_FB_SIGMA)
    # the blanked background is flat: DIS's flow there is smooth, consistent both ways and meaningless
    for conf, mask, c2f in ((c_ab, mask_a, crop_to_frame_a), (c_ba, mask_b, crop_to_frame_b)):
        conf *= warp_similarity(_near_mask(mask, DIRECT_MASK_MARGIN), c2f, (crop_size, crop_size), 0, cv2.INTER_NEAREST)
    return np.concatenate([f_ab, f_ba, c_ab[..., None], c_ba[..., None]], axis=-1)


def direct_pair(seq: Sequence, t: int, u: int, dis: cv2.DISOpticalFlow) -> np.ndarray:
    """:func:`object_pair_flow` of the sequence's frames t and u."""
    c2f = seq.crop_to_frame
    return object_pair_flow(seq.image(t), seq.image(u), seq.mask(t), seq.mask(u), seq.bboxes[t], seq.bboxes[u],
                            c2f[t], c2f[u], seq.cfg.crop_size, dis)


@functools.lru_cache(maxsize=4)
def _pixel_grid(S: int) -> tuple[np.ndarray, np.ndarray]:
    r, c = np.mgrid[0:S, 0:S].astype(np.float32)
    return c, r


def compose_pairs(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Chain two pair flows: (t -> t + a) then (t + a -> t + a + b), both ``(S, S, 6)`` in the layout of
    :class:`~s3o_warp.data.flow.FlowPair`; returns the same for (t -> t + a + b).

    Forward ``f(p) = f1(p) + f2(p + f1(p))`` with confidence ``c1(p) c2(p + f1(p))``; backward
    ``b(q) = b2(q) + b1(q + b2(q))`` with ``c2b(q) c1b(q + b2(q))``; bilinear samples, confidence 0 where the
    sample point leaves the middle crop.
    """
    S = first.shape[0]
    gx, gy = _pixel_grid(S)
    a = np.asarray(first, dtype=np.float32)
    b = np.asarray(second, dtype=np.float32)

    def chain(hop1: np.ndarray, hop2: np.ndarray, flow: tuple[int, int], conf: int) -> np.ndarray:
        mx, my = gx + hop1[..., flow[0]], gy + hop1[..., flow[1]]
        s = cv2.remap(np.ascontiguousarray(hop2[..., [flow[0], flow[1], conf]]), mx, my, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE)
        s[..., 0] += hop1[..., flow[0]]
        s[..., 1] += hop1[..., flow[1]]
        s[..., 2] *= hop1[..., conf] * ((mx >= -0.5) & (mx <= S - 0.5) & (my >= -0.5) & (my <= S - 0.5))
        return s

    f = chain(a, b, (0, 1), 4)
    bw = chain(b, a, (2, 3), 5)
    return np.concatenate([f[..., :2], bw[..., :2], f[..., 2:], bw[..., 2:]], axis=-1)


def pick_pairs(direct: np.ndarray, composed: np.ndarray) -> np.ndarray:
    """Per pixel and direction, the flow (and confidence) of whichever of two ``(S, S, 6)`` pair arrays is more
    confident; ties go to ``composed``."""
    use_f = direct[..., 4] > composed[..., 4]
    use_b = direct[..., 5] > composed[..., 5]
    sel = np.stack([use_f, use_f, use_b, use_b, use_f, use_b], axis=-1)
    return np.where(sel, direct, composed).astype(np.float32)


@dataclass
class LongFlowCache:
    """On-disk flow for every pair (t, t + g) of the given gaps; pairs are memory-mapped on access.

    Attributes:
        cache_dir: folder holding the ``lflow_<key>.npy`` files (and gap 1's ``flow_<key>.npy``).
        gaps: the gaps, ascending.
        files: ``files[g][t]`` holds pair (t, t + g), t = 0 .. T - 1 - g.
        crop_size: S.
        crop_to_frame: ``(T, 3, 3) float64`` crop -> frame transforms the flows refer to.
        computed: pairs with g > 1 computed by the call that made this object.
        hits: pairs with g > 1 found in the cache by that call.
    """

    cache_dir: Path
    gaps: tuple[int, ...]
    files: dict[int, list[Path]]
    crop_size: int
    crop_to_frame: np.ndarray
    computed: int = 0
    hits: int = 0

    def pair(self, t: int, gap: int) -> FlowPair:
        """Pair (t, t + gap), memory-mapped."""
        if gap not in self.files:
            raise KeyError(f"gap {gap} was not computed (gaps: {list(self.gaps)})")
        path = self.files[gap][t]
        try:
            arr = np.load(path, mmap_mode="r")
        except (OSError, ValueError) as exc:
            raise InputError(f"{path}: cannot read this flow cache file ({exc}); delete it to recompute") from None
        return FlowPair.from_array(arr)


def _direct_payload(seq: Sequence, t: int, gap: int, cfg: DataConfig) -> dict:
    return {**pair_payload(seq, t, t + gap, cfg), "mask_margin": DIRECT_MASK_MARGIN, "canvas": "mask boxes"}


def long_pair_keys(seq: Sequence, gaps, cfg: DataConfig | None = None) -> dict[int, list[str]]:
    """SHA-256 hex key of every pair (t, t + g): gap 1 :func:`~s3o_warp.data.flow.pair_key`, longer gaps the keys of
    the two hops they are composed of plus, up to :data:`DIRECT_MAX_GAP`, the direct pair's content and settings."""
    cfg = cfg or seq.cfg
    split = hop_split(gaps)
    T = seq.num_frames
    keys = {1: [pair_key(seq, t, cfg) for t in range(T - 1)]}
    for g in sorted(split):
        a, b = split[g]
        keys[g] = []
        for t in range(T - g):
            direct = _direct_payload(seq, t, g, cfg) if g <= DIRECT_MAX_GAP else None
            payload = {"format": LONG_FLOW_FORMAT_VERSION, "gap": g, "direct": direct,
                       "hops": [keys[a][t], keys[b][t + a]]}
            keys[g].append(hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest())
    return keys


def compute_long_flow(
    seq: Sequence, cache_dir: str | Path, gaps=None, cfg: DataConfig | None = None
) -> LongFlowCache:
    """Flow for every pair (t, t + g) of ``seq`` and every gap g, computed once and cached under ``cache_dir``.

    Gap 1 is :func:`~s3o_warp.data.flow.compute_flow` (the fit's own cache). Longer gaps are computed in ascending
    order, one pair at a time (two decoded frames and two memory-mapped hops in memory), with a tqdm bar; a stop
    request (:mod:`s3o_warp.interrupt`) ends it between pairs, the pairs done so far cached.

    Args:
        seq: from :func:`s3o_warp.data.sequence.open_sequence`; its crops define the crop coordinates.
        cache_dir: e.g. ``<run>/cache``.
        gaps: the gaps (default :func:`default_gaps`); gaps not shorter than the clip are left out.
        cfg: flow settings; defaults to ``seq.cfg`` (see :func:`~s3o_warp.data.flow.compute_flow`).

    Returns:
        :class:`LongFlowCache`.

    Raises:
        ConfigError: bad gaps or flow settings.
        InputError: a frame that cannot be decoded (named).
    """
    cfg = cfg or seq.cfg
    T = seq.num_frames
    if T < 2:
        raise InputError(f"{seq.name}: flow needs at least 2 frames, got {T}")
    gaps = default_gaps(T) if gaps is None else tuple(sorted({int(g) for g in gaps}))
    split = hop_split(gaps)  # checks the gaps before anything is computed
    gaps = tuple(g for g in gaps if g < T)
    split = {g: split[g] for g in gaps if g > 1}
    cache_dir = Path(cache_dir)
    S = cfg.crop_size
    first = compute_flow(seq, cache_dir, cfg)
    keys = long_pair_keys(seq, gaps, cfg)
    files: dict[int, list[Path]] = {1: list(first.files)}
    for g in split:
        files[g] = [cache_dir / f"lflow_{k[:40]}.npy" for k in keys[g]]
    todo = [(g, t) for g in split for t, f in enumerate(files[g]) if not (f.is_file() and _is_valid_file(f, S))]
    total = sum(len(files[g]) for g in split)
    dis = make_dis(cfg.flow_preset, FLOW_FINEST_SCALE) if any(g <= DIRECT_MAX_GAP for g, _ in todo) else None
    for k, (g, t) in enumerate(tqdm(todo, desc=f"{seq.name}: long-gap flow", unit="pair", leave=False, disable=None)):
        interrupt.check(f"the long-gap flow ({total - len(todo) + k} of {total} pairs cached)")
        a, b = split[g]
        arr = compose_pairs(np.load(files[a][t], mmap_mode="r"), np.load(files[b][t + a], mmap_mode="r"))
        if g <= DIRECT_MAX_GAP:
            arr = pick_pairs(direct_pair(seq, t, t + g, dis), arr)
        cache_dir.mkdir(parents=True, exist_ok=True)
        write_stream(files[g][t], lambda f: np.save(f, arr))
    log.info(
        "%s: long-gap flow, gaps %s: %d pairs (%d computed, %d cached) in %s",
        seq.name, ",".join(map(str, gaps)), total, len(todo), total - len(todo), cache_dir,
    )
    return LongFlowCache(cache_dir=cache_dir, gaps=gaps, files=files, crop_size=S, crop_to_frame=seq.crop_to_frame,
                         computed=len(todo), hits=total - len(todo))
