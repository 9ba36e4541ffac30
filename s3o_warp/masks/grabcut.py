"""The default segmenter, OpenCV and PyMaxflow only: GrabCut on the frame with the box, refined with the object's
motion, then carried through the video by optical flow, frame by frame, forward and backward, each frame by a graph
cut (:mod:`s3o_warp.masks.cut`) that weighs colour, motion and the previous frame's shape.

On the box's frame K the object's motion labels the box first: the background's motion between K and K +- gap is
one homography (fitted with RANSAC on the optical flow outside the box); pixels in the box that move otherwise
start GrabCut as probable object, the rest as probable background (a plain GrabCut rectangle where the
homography is not found, e.g. a textureless background). GrabCut then runs :data:`INIT_ITERATIONS` times. Where
the result does not fit the box (:data:`BOX_FIT`: what moved was the parallax of a rough background, not the object),
GrabCut runs again from the plain box and the result that fits the box better is kept. Its mask is then refined
(:func:`_refine_box`) by rounds of the graph cut in the box with the colour models learned from the mask and the
motion log-odds against the frames K +- gap: GrabCut's colours alone take in a background of the object's colours
(the grey wall behind DAVIS blackswan), which does not move as the object does.

From frame t to its neighbour t': the mask of t is warped to t' by the backward flow (DIS, the fit's flow
settings); pixels farther than a band (:data:`BAND`) outside it are background, and a graph cut decides the warped
mask and the band. Its evidence per pixel, as log-odds of object against background: the colour, with the
object's model learned on frame K (inside its mask) and kept fixed, and the background's learned on t' around the
object (a fixed object model keeps the background from leaking in over time); the motion, whether the pixel's flow
fits the object's (an affine map fitted on the warped mask) or the background's around it (the flow outside the
band spread inwards), weighted down where the forward and backward flows disagree: the background of the object's
colours (a goat's rocks, a black swan's water) does not move with it; and the shape, the warped mask softened at
its edge (:data:`SHAPE_WEIGHT`). Only what clearly moves otherwise than the background (the background's homography
fitted to the flow outside the band) where the forward and backward flows agree, in the warped mask's core, is
forced to be object (:data:`MOVING_MIN`): an object half hidden, whose sliver in sight the smoothness would cut
away. The rest of the warped mask is not: background uncovered behind a moving object, which the flow carries along
with it, would be kept for good; the band lets a limb that moves faster than the flow follows be found again. The
components of the result that lie on the warped mask are kept.

Each carried frame gets a confidence (:class:`Frame`): the least of the new mask's agreement with the flow-warped
one, the ratio of their areas, and the square root of the ratio of its area to the box frame's mask's scaled as the
flow scales the object. The confidence does not steer the masks; it says which frames to check (``s3o-masks`` flags
those under its threshold).

Where the mask vanishes (the object behind a post or a branch), the object is not lost at once: the largest of the
last masks found is moved on at its own speed (a similarity fitted to the flow on it), written for the hidden frames
(flagged), and searched for there, for up to :data:`MAX_HIDDEN` frames; past them it is lost (:class:`ObjectLost`).

Every GrabCut runs with OpenCV's random generator seeded and the graph cut is exact, so a video's masks repeat bit
for bit.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable, Iterator
from typing import NamedTuple

import cv2
import numpy as np

from s3o_warp.data.crops import mask_bbox
from s3o_warp.data.flow import FLOW_FINEST_SCALE, make_dis
from s3o_warp.masks import cut

INIT_ITERATIONS = 10
"""GrabCut iterations on the box's frame (from 5 to 10 the box frame's IoU rose 0.02-0.10 on DAVIS cows and dog)."""

MOTION_GAP = 2
"""Frames between the box's frame and the frames whose motion labels the box (1 moves the object too little)."""

MOTION_SIDE = 640
"""The motion labels are computed on frames scaled down to this longer side (pixels)."""

HOMOGRAPHY_INLIERS = 0.5
"""Fewest inliers (fraction of the flow samples outside the box) for the background's motion to be one homography."""

ROI_PAD = 0.4
"""Each step works in the previous mask's box grown by this fraction of its longer side (plus :data:`ROI_MARGIN`)."""

ROI_MARGIN = 16
"""Pixels added on every side of the working region."""

WORK_SIDE = 720
"""Longer side (pixels) the working region is scaled down to when larger (phone videos): the graph cut's cost grows
with the pixel count."""

BAND = 0.16
"""Width of the band outside the warped mask that the graph cut decides, as a fraction of the square root of its
area; also how far the background's flow is spread into the band. Chosen when GrabCut decided the band: at 0.08
instead, mean / worst-frame IoU: DAVIS cows 0.828 / 0.761 (0.825 / 0.730 here), dog 0.906 / 0.819 (0.905 / 0.819),
but the Fox 0.961 / 0.840 (0.975 / 0.934) and the horse 0.957 / 0.929 (0.963 / 0.931)."""

MOVING_MIN = 2.0
"""Pixels a frame: the least motion against the background's that forces a pixel of the warped mask's core to be
object while carrying a mask (:func:`_moving`). Forced only in the core (the warped mask eroded by
:data:`MOVING_ERODE`): forced in the whole band too (as when GrabCut decided the band), the rocks' parallax and the
water's ripples, which move otherwise than the background's homography, took DAVIS goat to 0.197 mean IoU and
blackswan to 0.329 (0.710 and 0.822 in the core only); forced nowhere, 0.720 and 0.835, but the disc going behind a
post of its own colour (``tests/masks``) was cut away as a sliver by the smoothness at the post's edge, and lost."""

MOVING_FACTOR = 4.0
"""... and at least this multiple of the background's own median residual."""

MOVING_FB = 0.5
"""Pixels: the most the backward and forward flow may disagree where motion marks a pixel as object (on the synthetic
Fox this kept 3,600-4,300 of the object's moving pixels and 16-120 of the background's, of 2,600-3,200 without)."""

MOVING_ERODE = 0.03
"""While carrying a mask, the warped mask's core: the warped mask eroded by this fraction of the square root of its
area (at least 2 pixels), the flow blurring the motion over the object's edge. The object's motion (an affine map)
is fitted to the flow there, and its pixels that clearly move (:func:`_moving`) are forced to be object."""

SHAPE_WEIGHT = 1.0
"""While carrying a mask: the weight of the shape log-odds (the warped mask, :func:`s3o_warp.masks.cut.shape_log_odds`)
beside the colour's and the motion's. This and the two below are not tuned one by one: measured only together with
the motion (docs/results.md)."""

SHAPE_SCALE = 0.5
"""... its signed distance to the warped mask's edge is divided by this fraction of :data:`BAND`'s width (at least 1
pixel) ..."""

SHAPE_CLIP = 2.0
"""... and clipped to +- this: deep inside (or far outside) the warped mask the shape outweighs a colour that is
unsure (|log-odds| < 2) but not one that is sure, nor motion that clearly differs."""

BOX_REFINE_ITERATIONS = 5
"""On the box's frame, GrabCut's mask is refined by this many rounds of the colour and motion graph cut
(:func:`_refine_box`; fewer where the mask stops changing). Mean IoU of DAVIS blackswan / dog at 0 (no refinement),
1, 2 and 5 rounds, with no moving pixel forced while carrying: 0.398 / 0.911, 0.461 / 0.895, 0.767 / 0.895, 0.835 /
0.896: the grey wall GrabCut takes in with the swan goes only over several rounds; the dog loses 0.015 to it at any
count."""

BOX_MOTION_SIGMA = 0.16
"""On the box's frame: how far the background's flow is spread into the box (normalised convolution), as a fraction
of the square root of the box's area (:data:`BAND`'s width for an object that fills its box). Not tuned: measured
only with the rest of the refinement (docs/results.md)."""

OBJECT_ERODE = 0.05
"""The object's colour model is learned on the box frame's mask eroded by this fraction of the square root of its
area: ground the box frame's GrabCut took in between the legs would otherwise count as object in every frame. Mean
/ worst-frame IoU from the whole mask -> eroded: DAVIS cows 0.825 / 0.730 -> 0.850 / 0.741, dog 0.905 / 0.819 ->
0.907 / 0.819, Fox 0.975 / 0.934 -> 0.974 / 0.934, horse 0.963 / 0.931 -> 0.962 / 0.932."""

COLOUR_SAMPLES = 20000
"""Pixels drawn to learn each colour model (all of them when fewer)."""

SEED = 0
"""OpenCV's random generator seed before every GrabCut (its colour models start from k-means)."""

log = logging.getLogger(__name__)

Box = tuple[int, int, int, int]
"""``(x0, y0, x1, y1)`` inclusive frame pixels."""


class ObjectLost(Exception):
    """The object was not found from frame ``frame`` on (for more than :data:`MAX_HIDDEN` frames) while carried from
    the box on frame ``anchor``; or, with ``frame == anchor``, nothing was segmented in that box."""

    def __init__(self, frame: int, anchor: int, area: int, anchor_area: int):
        super().__init__(f"object lost at frame {frame}")
        self.frame, self.anchor, self.area, self.anchor_area = frame, anchor, area, anchor_area


LOST_FRACTION = 0.1
"""A mask smaller than this fraction of the expected area (the box frame's mask's, scaled as the flow scales the
object) counts as lost: the object is hidden from there."""

FOUND_FRACTION = 0.25
"""A hidden object counts as found again where its mask is this fraction of the mask carried through the hidden
frames (the largest of the last :data:`MAX_HIDDEN` found, moved on at its own speed)."""

MAX_HIDDEN = 10
"""Frames a hidden object is carried on before it counts as lost (the command stops and names the frame)."""

EDGE_SLACK = 0.03
"""Of the square root of the object's area: how far from the flow-warped mask's edge the new mask may differ from it
without lowering the frame's confidence (the flow's own error at the edge)."""

BOX_FIT = 0.3
"""On the box's frame, a mask whose bounding box overlaps the box by less than this (IoU) is made again from the plain
box, and the one that fits the box better is kept: on DAVIS goat the motion start took a red rock below the box
(its bounding box 0.06 of the box; frame 0 IoU 0.00, 0.73 from the plain box), where the rough slope's parallax is no
one homography. At 0.7 it also replaced dance-twirl's frame-0 mask (fit 0.48, IoU 0.42) by another as wrong (fit
0.58, IoU 0.42) that carried worse (mean 0.436 -> 0.293)."""


def _grabcut(image: np.ndarray, labels: np.ndarray, models=None, iterations: int = 1):
    """GrabCut in place on ``labels`` (``GC_*`` values); returns the object pixels as a bool array."""
    cv2.setRNGSeed(SEED)
    bgd, fgd = models if models is not None else (np.zeros((1, 65)), np.zeros((1, 65)))
    cv2.grabCut(np.ascontiguousarray(image), labels, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    return (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)


def _sample(pixels: np.ndarray, n: int = COLOUR_SAMPLES) -> np.ndarray:
    if len(pixels) <= n:
        return pixels
    return pixels[np.random.default_rng(SEED).choice(len(pixels), n, replace=False)]


def colour_models(object_pixels: np.ndarray, background_pixels: np.ndarray):
    """GrabCut's two colour models (Gaussian mixtures, OpenCV's ``(1, 65)`` float64 layout) learned from ``(N, 3)``
    uint8 pixel samples: ``(background, object)``."""
    fg, bg = _sample(object_pixels), _sample(background_pixels)
    img = np.concatenate([fg, bg])[:, None, :].astype(np.uint8)
    lab = np.concatenate([np.full(len(fg), cv2.GC_FGD), np.full(len(bg), cv2.GC_BGD)])[:, None].astype(np.uint8)
    models = (np.zeros((1, 65)), np.zeros((1, 65)))
    _grabcut(img, lab, models, iterations=0)  # 0 iterations: the models from the labelled samples, nothing else
    return models


def _keep_object(mask: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """The components of ``mask`` that lie mostly on ``prior``, and the largest one."""
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 2:
        return mask
    on_prior = np.bincount(lab[prior], minlength=n)
    keep = on_prior > 0.5 * stats[:, cv2.CC_STAT_AREA]
    keep[1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))] = True
    keep[0] = False
    return keep[lab]


def _grey(image: np.ndarray, scale: float = 1.0) -> np.ndarray:
    if scale != 1.0:
        image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def motion_residual(image: np.ndarray, other: np.ndarray, box: Box, dis: cv2.DISOpticalFlow) -> np.ndarray | None:
    """How far each pixel of ``image`` moves, towards ``other``, from where the background's motion (one homography,
    RANSAC on the flow outside ``box``) takes it: ``(H, W) float32`` frame pixels, or None when the background's
    motion is not one homography (fewer than :data:`HOMOGRAPHY_INLIERS` inliers)."""
    H, W = image.shape[:2]
    scale = min(1.0, MOTION_SIDE / max(H, W))
    a, b = _grey(image, scale), _grey(other, scale)
    flow = dis.calc(a, b, None)
    h, w = a.shape
    x0, y0, x1, y1 = (int(v * scale) for v in box)
    outside = np.ones((h, w), bool)
    outside[max(0, y0 - 2) : y1 + 3, max(0, x0 - 2) : x1 + 3] = False
    residual = _residual(flow, outside)
    if residual is None:
        return None
    return cv2.resize(residual, (W, H), interpolation=cv2.INTER_LINEAR) / scale


def segment_box(image: np.ndarray, box: Box, neighbours: list[np.ndarray], dis: cv2.DISOpticalFlow) -> np.ndarray:
    """The object in ``box`` on ``image`` (``(H, W, 3)`` uint8): GrabCut started from the object's motion against
    ``neighbours`` (frames :data:`MOTION_GAP` before and after), then refined by the colour and motion graph cut
    (:func:`_refine_box`); see the module docstring. ``(H, W) bool``."""
    H, W = image.shape[:2]
    x0, y0, x1, y1 = box
    residuals = [r for r in (motion_residual(image, n, box, dis) for n in neighbours) if r is not None]
    labels = np.full((H, W), cv2.GC_BGD, np.uint8)
    inside = np.s_[y0 : y1 + 1, x0 : x1 + 1]
    labels[inside] = cv2.GC_PR_FGD
    if residuals:
        moving = np.max(residuals, axis=0)[inside]
        # Otsu's threshold on the residual in the box, at 1/20 pixel
        scaled = np.clip(moving * 20.0, 0, 255).astype(np.uint8)
        t, _ = cv2.threshold(scaled, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        labels[inside] = np.where(moving > t / 20.0, cv2.GC_PR_FGD, cv2.GC_PR_BGD)
        if not (labels == cv2.GC_PR_FGD).any():
            labels[inside] = cv2.GC_PR_FGD
    mask = _keep_object(_grabcut(image, labels, iterations=INIT_ITERATIONS), np.zeros((H, W), bool))
    if residuals and _box_fit(mask, box) < BOX_FIT:
        # what moved was not the object (a rough background's parallax): the plain box instead, where it fits better
        labels[:] = cv2.GC_BGD
        labels[inside] = cv2.GC_PR_FGD
        plain = _keep_object(_grabcut(image, labels, iterations=INIT_ITERATIONS), np.zeros((H, W), bool))
        if _box_fit(plain, box) > _box_fit(mask, box):
            mask = plain
    if mask.any():
        mask = _refine_box(image, box, neighbours, dis, mask)
    return mask


def _refine_box(image: np.ndarray, box: Box, neighbours: list[np.ndarray], dis: cv2.DISOpticalFlow,
                mask: np.ndarray) -> np.ndarray:
    """``mask`` (GrabCut's, on the box's frame) refined by up to :data:`BOX_REFINE_ITERATIONS` rounds of the graph
    cut in ``box`` (outside it: background): each round learns the colour models from the mask (the object's on it
    eroded by :data:`OBJECT_ERODE`, the background's off it) and adds :data:`s3o_warp.masks.cut.MOTION_WEIGHT` x
    the motion log-odds against each of ``neighbours`` (averaged), the object's motion fitted on the eroded mask
    and the background's sampled outside the box. Stops where the mask no longer changes (or vanishes)."""
    H, W = image.shape[:2]
    x0, y0, x1, y1 = box
    inside = np.zeros((H, W), bool)
    inside[y0 : y1 + 1, x0 : x1 + 1] = True
    g = _grey(image)
    flows = []
    for n in neighbours:
        gn = _grey(n)
        back = dis.calc(g, gn, None)
        fwd = dis.calc(gn, g, None)
        flows.append((back, cut.fb_error(back, fwd)))
    c = np.s_[max(0, y0 - 1) : y1 + 2, max(0, x0 - 1) : x1 + 2]
    sigma = BOX_MOTION_SIGMA * math.sqrt((x1 - x0 + 1) * (y1 - y0 + 1))
    for _ in range(BOX_REFINE_ITERATIONS):
        side = math.sqrt(mask.sum())
        core = cv2.erode(mask.astype(np.uint8), _disk(max(1, int(OBJECT_ERODE * side)))) > 0
        if not core.any():
            break
        models = colour_models(image[core], image[~mask])
        lo = cut.colour_log_odds(image[c], models)
        if flows:
            lo += cut.MOTION_WEIGHT * np.mean([cut.motion_log_odds(b, core, ~inside, sigma, fb)[c] for b, fb in flows],
                                              axis=0)
        new = np.zeros((H, W), bool)
        new[c] = cut.graph_cut(image[c], lo, fixed_bg=~inside[c])
        new = _keep_object(new, mask)
        if not new.any() or (new == mask).all():
            break
        mask = new
    return mask


def _box_fit(mask: np.ndarray, box: Box) -> float:
    """IoU of ``mask``'s bounding box with ``box`` (0 for an empty mask)."""
    b = mask_bbox(mask)
    if b is None:
        return 0.0
    ix = max(0, min(b[2], box[2]) - max(b[0], box[0]) + 1) * max(0, min(b[3], box[3]) - max(b[1], box[1]) + 1)
    area = lambda q: (q[2] - q[0] + 1) * (q[3] - q[1] + 1)  # noqa: E731
    return ix / (area(b) + area(box) - ix)


def _residual(flow: np.ndarray, samples: np.ndarray) -> np.ndarray | None:
    """|x + flow(x) - hom(x)| per pixel, hom the homography RANSAC fits to ``flow`` on the ``samples`` pixels; None
    when fewer than :data:`HOMOGRAPHY_INLIERS` of them fit it."""
    h, w = flow.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    idx = np.flatnonzero(samples)
    if len(idx) < 16:
        return None
    idx = idx[:: max(1, len(idx) // 4000)]
    src = np.stack([xx.ravel()[idx], yy.ravel()[idx]], 1)
    hom, inliers = cv2.findHomography(src, src + flow.reshape(-1, 2)[idx], cv2.RANSAC, 1.0)
    if hom is None or inliers.mean() < HOMOGRAPHY_INLIERS:
        return None
    pts = np.stack([xx, yy], -1)
    predicted = cv2.perspectiveTransform(pts.reshape(-1, 1, 2), hom).reshape(h, w, 2)
    return np.linalg.norm(pts + flow - predicted, axis=-1)


def _moving(back: np.ndarray, fb: np.ndarray, background: np.ndarray, erode: int) -> np.ndarray | None:
    """Pixels that clearly move otherwise than the background: ``back``'s residual against its homography on
    ``background`` over :data:`MOVING_FACTOR` x the background's median (and :data:`MOVING_MIN` pixels), eroded by
    ``erode`` pixels (the flow blurs motion over the object's edge), where ``back``'s forward-backward error ``fb``
    (:func:`s3o_warp.masks.cut.fb_error`) is under :data:`MOVING_FB` pixels (flow dragged over a smooth background
    by a fast object does not come back). None without a background homography."""
    r = _residual(back, background)
    if r is None:
        return None
    t = max(MOVING_MIN, MOVING_FACTOR * float(np.median(r[background])))
    agree = fb < MOVING_FB
    moving = (cv2.erode((r > t).astype(np.uint8), _disk(erode)) > 0) & agree
    return cv2.erode(moving.astype(np.uint8), _disk(1)) > 0


def _disk(r: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


class Step(NamedTuple):
    """One frame's mask carried from its neighbour's (:func:`carry`)."""

    mask: np.ndarray
    """``(H, W) bool``."""
    prior: np.ndarray
    """The neighbour's mask warped by the flow (or the prior given): where the object was expected, ``(H, W) bool``."""
    agreement: float
    """How well ``mask`` and ``prior`` agree (:func:`_agreement`)."""
    velocity: tuple[float, float]
    """The object's motion from the neighbour, frame pixels ``(dx, dy)``."""
    growth: float
    """How the object's area grows from the neighbour, by the flow (a similarity fitted to it)."""


def carry(previous_image: np.ndarray, image: np.ndarray, previous_mask: np.ndarray, object_pixels: np.ndarray,
          dis: cv2.DISOpticalFlow, prior: np.ndarray | None = None) -> Step:
    """The mask of ``image`` from its neighbour's (``previous_mask`` on ``previous_image``) and the object's colour
    samples ``object_pixels`` (``(N, 3)`` uint8, from the box's frame); see the module docstring. ``prior``: where
    the object is expected on ``image`` (``(H, W) bool``) instead of the flow-warped ``previous_mask`` (an object
    hidden behind something, whose flow is the occluder's)."""
    H, W = previous_mask.shape
    x0, y0, x1, y1 = mask_bbox(previous_mask if prior is None else prior | previous_mask)
    pad = int(ROI_PAD * max(x1 - x0, y1 - y0)) + ROI_MARGIN
    X0, Y0, X1, Y1 = max(0, x0 - pad), max(0, y0 - pad), min(W, x1 + pad + 1), min(H, y1 + pad + 1)
    scale = min(1.0, WORK_SIDE / max(X1 - X0, Y1 - Y0))
    size = (max(1, round((X1 - X0) * scale)), max(1, round((Y1 - Y0) * scale)))

    def work(a: np.ndarray, interp=cv2.INTER_AREA) -> np.ndarray:
        a = a[Y0:Y1, X0:X1]
        return a if scale == 1.0 else cv2.resize(a, size, interpolation=interp)

    def full(a: np.ndarray) -> np.ndarray:
        out = np.zeros((H, W), bool)
        if scale != 1.0:
            a = cv2.resize(a.astype(np.float32), (X1 - X0, Y1 - Y0), interpolation=cv2.INTER_LINEAR) > 0.5
        out[Y0:Y1, X0:X1] = a
        return out

    roi, prev_roi = work(image), work(previous_image)
    back = dis.calc(_grey(roi), _grey(prev_roi), None)  # at a pixel of image: where it was in previous_image
    h, w = roi.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    if prior is None:
        prev_m = work(previous_mask.astype(np.float32), cv2.INTER_LINEAR)
        warped = cv2.remap(prev_m, xx + back[..., 0], yy + back[..., 1], cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT) > 0.5
    else:
        warped = work(prior.astype(np.float32), cv2.INTER_LINEAR) > 0.5
    if not warped.any():
        return Step(np.zeros((H, W), bool), full(warped), 0.0, (0.0, 0.0), 1.0)
    velocity, growth = _object_motion(back, warped, scale)
    side = math.sqrt(warped.sum())
    band = max(3, int(BAND * side))
    outer = cv2.dilate(warped.astype(np.uint8), _disk(band)) > 0
    if not (~outer).any():  # the region is all object: nothing to learn the background from
        fg = warped
    else:
        fwd = dis.calc(_grey(prev_roi), _grey(roi), None)
        core = cv2.erode(warped.astype(np.uint8), _disk(max(2, int(MOVING_ERODE * side)))) > 0
        models = colour_models(object_pixels, roi[~outer])
        ys, xs = np.nonzero(outer)
        c = np.s_[max(0, ys.min() - 1) : ys.max() + 2, max(0, xs.min() - 1) : xs.max() + 2]  # the cut's region
        log_odds = cut.colour_log_odds(roi[c], models)
        fb = cut.fb_error(back, fwd)
        motion = cut.motion_log_odds(back, core if core.any() else warped, ~outer, band, fb)
        log_odds += cut.MOTION_WEIGHT * motion[c]
        log_odds += SHAPE_WEIGHT * cut.shape_log_odds(warped[c], max(1.0, SHAPE_SCALE * band), SHAPE_CLIP)
        moving = _moving(back, fb, ~outer, max(2, int(MOVING_ERODE * side)))
        fg = np.zeros((h, w), bool)
        fg[c] = cut.graph_cut(roi[c], log_odds, fixed_bg=~outer[c],
                              fixed_fg=None if moving is None else (moving & core)[c])
        fg = _keep_object(fg, warped)
    return Step(full(fg), full(warped), _agreement(fg, warped), velocity, growth)


def _agreement(mask: np.ndarray, prior: np.ndarray) -> float:
    """IoU of ``mask`` and ``prior`` where they differ by more than the flow's error at the edge: pixels within
    :data:`EDGE_SLACK` x the square root of ``prior``'s area of its edge count as agreeing."""
    slack = _disk(max(1, int(EDGE_SLACK * math.sqrt(prior.sum()))))
    p = prior.astype(np.uint8)
    edge = (cv2.dilate(p, slack) > 0) & ~(cv2.erode(p, slack) > 0)
    union = (mask | prior).sum()
    return float(1.0 - ((mask ^ prior) & ~edge).sum() / max(1, union))


def _object_motion(back: np.ndarray, region: np.ndarray, scale: float) -> tuple[tuple[float, float], float]:
    """The object's motion from the previous frame, from the backward flow ``back`` on ``region`` (working pixels,
    ``scale`` of the frame's): its centre's ``(dx, dy)`` in frame pixels and how its area grows, from a similarity
    (RANSAC) fitted to the flow; the median flow and no growth where none fits."""
    ys, xs = np.nonzero(region)
    idx = np.arange(0, len(xs), max(1, len(xs) // 2000))
    here = np.stack([xs[idx], ys[idx]], 1).astype(np.float32)
    there = here + back[ys[idx], xs[idx]]
    m = None
    if len(idx) > 2:
        m = cv2.estimateAffinePartial2D(there, here, method=cv2.RANSAC, ransacReprojThreshold=1.0)[0]
    if m is None or not 0.5 < abs(np.linalg.det(m[:, :2])) < 2.0:  # none, or no motion from one frame to the next
        return tuple(float(-np.median(back[..., i][region]) / scale) for i in (0, 1)), 1.0
    centre = here.mean(0)
    before = np.linalg.solve(m[:, :2], centre - m[:, 2])
    velocity = (float((centre[0] - before[0]) / scale), float((centre[1] - before[1]) / scale))
    return velocity, float(abs(np.linalg.det(m[:, :2])))


def _shifted(mask: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``mask`` moved by ``(dx, dy)`` pixels."""
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(mask.astype(np.uint8), m, mask.shape[::-1], flags=cv2.INTER_NEAREST) > 0


class Frame(NamedTuple):
    """One frame's mask as :func:`segment_video` yields it."""

    k: int
    mask: np.ndarray
    """``(H, W) bool``."""
    confidence: float | None
    """From 0 to 1 (1 on a box's frame, 0 where the object is carried hidden; None from a segmenter without one):
    the least of how well the mask agrees with its neighbour's moved by the optical flow (:func:`_agreement`), the
    ratio of their areas, and the square root of the ratio of its area to the box frame's mask's scaled as the flow
    scales the object (a slow drift, which no single step shows)."""
    carried: bool
    """The object was not found in this frame (hidden, or lost to the segmenter): ``mask`` is where it was last
    seen, moved on at its last speed."""


def segment_video(read: Callable[[int], np.ndarray], n: int, boxes: dict[int, Box],
                  flow_preset: str = "medium") -> Iterator[Frame]:
    """Masks of frames 0..n-1 from boxes on some of them, each frame once (in the order they are made, not 0..n-1).

    Each box's frame is segmented (:func:`segment_box`) and its mask carried (:func:`carry`) forward and backward
    to halfway to the next box (to the ends of the video past the first and last box). Where the mask vanishes
    (under :data:`LOST_FRACTION` of the expected area) the object is carried on, hidden, for up to
    :data:`MAX_HIDDEN` frames: the largest of the last masks found, moved on at its own speed, and searched for
    there until a mask of :data:`FOUND_FRACTION` of it is found.

    Args:
        read: frame k as ``(H, W, 3)`` uint8 RGB.
        n: the number of frames.
        boxes: ``{frame: (x0, y0, x1, y1)}``, inclusive frame pixels, checked by the caller.
        flow_preset: ``DataConfig.flow_preset``.

    Raises:
        ObjectLost: the object stayed hidden for more than :data:`MAX_HIDDEN` frames (or left the picture); or nothing
            was segmented in a box (``frame == anchor``).
    """
    dis = make_dis(flow_preset, FLOW_FINEST_SCALE)
    anchors = sorted(boxes)
    for i, a in enumerate(anchors):
        lo = 0 if i == 0 else (anchors[i - 1] + a) // 2 + 1
        hi = n - 1 if i == len(anchors) - 1 else (a + anchors[i + 1]) // 2
        image = read(a)
        neighbours = [read(k) for k in (a - MOTION_GAP, a + MOTION_GAP) if 0 <= k < n]
        mask = segment_box(image, boxes[a], neighbours, dis)
        area = int(mask.sum())
        if not area:
            raise ObjectLost(a, a, 0, 0)
        yield Frame(a, mask, 1.0, False)
        core = cv2.erode(mask.astype(np.uint8), _disk(max(1, int(OBJECT_ERODE * math.sqrt(area))))) > 0
        object_pixels = image[core if core.any() else mask]
        for stop, step in ((hi, 1), (lo, -1)):
            prev_image, prev_mask = image, mask
            expected = float(area)  # the box frame's mask area, scaled as the flow scales the object
            recent = deque([(a, mask, (0.0, 0.0))], maxlen=MAX_HIDDEN)  # the masks found last: frame, mask, motion
            hidden, whole = 0, None
            for k in range(a + step, stop + step, step):
                cur = read(k)
                prior = None
                if hidden:
                    prior = _shifted(whole[1], *(v * abs(k - whole[0]) for v in whole[2]))
                s = carry(prev_image, cur, prev_mask, object_pixels, dis, prior)
                got = int(s.mask.sum())
                if not hidden:
                    expected *= s.growth
                if got >= (FOUND_FRACTION if hidden else LOST_FRACTION) * expected:
                    hidden = 0
                    recent.append((k, s.mask, s.velocity))
                    step_area = min(got, s.prior.sum()) / max(got, s.prior.sum())
                    drift = math.sqrt(min(got, expected) / max(got, expected))
                    log.debug("frame %d: agreement %.3f, area against the flow's %.3f, drift from the box's %.3f",
                              k, s.agreement, step_area, drift)
                    yield Frame(k, s.mask, min(s.agreement, step_area, drift), False)
                    prev_mask = s.mask
                else:
                    if not hidden:  # the largest of the masks found last, moved on at its own speed
                        whole = max(recent, key=lambda r: int(r[1].sum()))
                        expected = float(whole[1].sum())
                    hidden += 1
                    prev_mask = _shifted(whole[1], *(v * abs(k - whole[0]) for v in whole[2]))
                    if hidden > MAX_HIDDEN or not prev_mask.any():
                        raise ObjectLost(k - step * (hidden - 1), a, got, area)
                    yield Frame(k, prev_mask, 0.0, True)
                prev_image = cur
