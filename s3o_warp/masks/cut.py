"""The graph cut that carries a mask from frame to frame (and refines the box frame's): each pixel's evidence for
object against background, as a log-odds from three sources, and the usual contrast-sensitive smoothness between
neighbours (GrabCut's), cut by PyMaxflow (Boykov-Kolmogorov).

- Colour (:func:`gmm_log_likelihood`): the object's and the background's Gaussian mixtures (GrabCut's models).
- Motion (:func:`motion_log_odds`): does the pixel move as the object does, or as the background around it does?
  The object's motion is one affine map fitted (RANSAC) to the optical flow on where the object is expected; the
  background's is the flow outside the band, spread inwards by normalised convolution, so it follows the
  background's own parallax (rocks in front of a far slope) instead of one homography. Where the two predict the
  same flow, motion says nothing; where the flow is unreliable (forward and backward disagree), neither.
- Shape (:func:`shape_log_odds`): the previous mask moved by the flow, softened by the distance to its edge.

The colour models alone cannot tell a goat from the rocks it stands on, nor a black swan from dark water; their
motion can.
"""

from __future__ import annotations

import math

import cv2
import maxflow
import numpy as np

GAMMA = 50.0
"""Weight of the contrast-sensitive smoothness between neighbours (GrabCut's)."""

MOTION_SCALE = 1.0
"""Working pixels: the flow error the Cauchy motion likelihoods treat as a match (their scale): a pixel 1 pixel off a
motion still half fits it. Like the weights below, not tuned one by one: measured only with the whole segmenter
(docs/results.md, "Masks from a box")."""

MOTION_WEIGHT = 2.0
"""The motion log-odds' weight against the colour's: with the motion at this weight DAVIS goat came to 0.71 mean IoU
(0.20 with GrabCut on colour alone)."""

MOTION_OUTLIER = 1.5
"""Cap on the object's motion term, ``log(1 + (d_o / s)^2)``: a pixel that fits neither motion (a leg moving faster
than the object's affine map, the flow's error at an edge) is not pushed to the background by missing the object's
motion alone; only a pixel that also fits the background's is."""

FB_SCALE = 1.0
"""Working pixels: forward-backward disagreement at which the motion evidence falls to exp(-1) of itself."""

COLOUR_CLIP = 8.0
"""The colour log-odds are clipped to +- this: the mixtures are overconfident far from their samples, and an
unclipped colour that neither model holds would outvote the motion and the shape."""


def gmm_log_likelihood(model: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """log p(pixel) under one of GrabCut's Gaussian mixtures (OpenCV's ``(1, 65)`` float64 layout: 5 weights, 5
    means, 5 covariances) for ``(..., 3)`` pixels; ``(...)`` float32."""
    m = np.asarray(model, np.float64).ravel()
    weights, means, covs = m[:5], m[5:20].reshape(5, 3), m[20:65].reshape(5, 3, 3)
    x = pixels.reshape(-1, 3).astype(np.float32)
    out = np.full(len(x), -np.inf, np.float32)
    for w, mu, cov in zip(weights, means, covs):
        if w <= 0:
            continue
        u = np.linalg.cholesky(np.linalg.inv(cov)).astype(np.float32)  # inv(cov) = u u^T
        z = (x - mu.astype(np.float32)) @ u
        maha = (z * z).sum(1)
        lp = math.log(w) - 0.5 * math.log(np.linalg.det(cov)) - 1.5 * math.log(2 * math.pi)
        out = np.logaddexp(out, np.float32(lp) - 0.5 * maha)
    return out.reshape(pixels.shape[:-1]).astype(np.float32)


def colour_log_odds(image: np.ndarray, models) -> np.ndarray:
    """log p(colour | object) - log p(colour | background) per pixel, clipped to +-:data:`COLOUR_CLIP`; ``models``
    as :func:`s3o_warp.masks.grabcut.colour_models` gives them, ``(background, object)``."""
    bgd, fgd = models
    lo = gmm_log_likelihood(fgd, image) - gmm_log_likelihood(bgd, image)
    return np.clip(lo, -COLOUR_CLIP, COLOUR_CLIP)


def _affine_flow(flow: np.ndarray, region: np.ndarray, samples: int = 3000) -> np.ndarray | None:
    """The flow an affine map fitted (RANSAC) to ``flow`` on ``region`` predicts at every pixel; None when
    ``region`` holds too few pixels or no map fits."""
    ys, xs = np.nonzero(region)
    if len(xs) < 12:
        return None
    idx = np.arange(0, len(xs), max(1, len(xs) // samples))
    here = np.stack([xs[idx], ys[idx]], 1).astype(np.float32)
    m, _ = cv2.estimateAffine2D(here, here + flow[ys[idx], xs[idx]], method=cv2.RANSAC, ransacReprojThreshold=1.0)
    if m is None:
        return None
    h, w = flow.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    return np.stack([m[0, 0] * xx + m[0, 1] * yy + m[0, 2] - xx, m[1, 0] * xx + m[1, 1] * yy + m[1, 2] - yy], -1)


def _spread(flow: np.ndarray, region: np.ndarray, sigma: float) -> np.ndarray | None:
    """``flow`` on ``region`` spread over every pixel by normalised convolution (a Gaussian of ``sigma`` pixels,
    computed at a quarter of the resolution where ``sigma`` allows); None when ``region`` is empty."""
    if not region.any():
        return None
    h, w = region.shape
    f = max(1, min(4, int(sigma / 4)))
    small = (max(1, w // f), max(1, h // f))
    wgt = region.astype(np.float32)
    num = flow * wgt[..., None]
    if f > 1:
        wgt = cv2.resize(wgt, small, interpolation=cv2.INTER_AREA)
        num = cv2.resize(num, small, interpolation=cv2.INTER_AREA)
    s = sigma / f
    den = cv2.GaussianBlur(wgt, (0, 0), s, borderType=cv2.BORDER_CONSTANT)
    num = cv2.GaussianBlur(num, (0, 0), s, borderType=cv2.BORDER_CONSTANT)
    out = num / np.maximum(den, 1e-6)[..., None]
    # far from every sample the Gaussian's tail underflows: the nearest estimate instead
    if (den < 1e-6).any():
        filled = den >= 1e-6
        if not filled.any():
            return None
        _, lab = cv2.distanceTransformWithLabels((~filled).astype(np.uint8), cv2.DIST_L2, 5,
                                                 labelType=cv2.DIST_LABEL_PIXEL)
        src = np.zeros(lab.max() + 1, np.int64)
        src[lab[filled]] = np.flatnonzero(filled.ravel())
        out = out.reshape(-1, 2)[src[lab]].reshape(out.shape)
    if f > 1:
        out = cv2.resize(out, (w, h), interpolation=cv2.INTER_LINEAR)
    return out


def fb_error(back: np.ndarray, fwd: np.ndarray) -> np.ndarray:
    """Per pixel of the frame ``back`` starts from: how far ``fwd`` (the other frame's flow back to it) misses
    coming back, pixels."""
    h, w = back.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    there = cv2.remap(fwd, xx + back[..., 0], yy + back[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.linalg.norm(back + there, axis=-1)


def motion_log_odds(back: np.ndarray, obj: np.ndarray, background: np.ndarray, sigma: float,
                    fb: np.ndarray | None = None) -> np.ndarray:
    """How much more each pixel's flow fits the object's motion than the background's, as a log-odds (see the
    module docstring): ``log(1 + (d_b / s)^2) - min(log(1 + (d_o / s)^2), MOTION_OUTLIER)``, d_o and d_b the
    distances from the object's and the background's predicted flow and s :data:`MOTION_SCALE`, weighted down by
    the forward-backward error ``fb`` (by ``exp(-(fb / FB_SCALE)^2)``).

    Args:
        back: ``(h, w, 2)`` flow from this frame to its neighbour.
        obj: where the object is expected, ``(h, w) bool`` (its affine motion is fitted there).
        background: where the background surely is, ``(h, w) bool``.
        sigma: pixels: how far the background's flow is spread from where it is sampled.
        fb: ``(h, w)`` forward-backward error of ``back``, or None.

    Returns:
        ``(h, w) float32``; zeros where either motion cannot be estimated.
    """
    h, w = back.shape[:2]
    o = _affine_flow(back, obj)
    b = _spread(back, background, sigma)
    if o is None or b is None:
        return np.zeros((h, w), np.float32)
    d_o = np.linalg.norm(back - o, axis=-1) / MOTION_SCALE
    d_b = np.linalg.norm(back - b, axis=-1) / MOTION_SCALE
    lo = np.log1p(d_b**2) - np.minimum(np.log1p(d_o**2), MOTION_OUTLIER)
    if fb is not None:
        lo *= np.exp(-((fb / FB_SCALE) ** 2))
    return lo.astype(np.float32)


def shape_log_odds(prior: np.ndarray, scale: float, clip: float = 2.0) -> np.ndarray:
    """The expected mask ``prior`` (``(h, w) bool``) as a log-odds: the signed distance to its edge over ``scale``
    pixels (positive inside), clipped to +-``clip``."""
    p = prior.astype(np.uint8)
    inside = cv2.distanceTransform(p, cv2.DIST_L2, 3)
    outside = cv2.distanceTransform(1 - p, cv2.DIST_L2, 3)
    return np.clip((inside - outside) / scale, -clip, clip).astype(np.float32)


def graph_cut(image: np.ndarray, log_odds: np.ndarray, fixed_bg: np.ndarray | None = None,
              fixed_fg: np.ndarray | None = None, gamma: float = GAMMA) -> np.ndarray:
    """The labelling that minimises sum of unary costs (``log_odds`` for object against background, per pixel)
    plus GrabCut's contrast-sensitive smoothness on the 8-neighbourhood of ``image`` (``(h, w, 3)`` uint8);
    ``fixed_bg`` / ``fixed_fg`` pixels are forced. Returns the object pixels, ``(h, w) bool``."""
    h, w = log_odds.shape
    img = image.astype(np.float32)
    shifts = ((0, 1, 1.0), (1, 0, 1.0), (1, 1, 1 / math.sqrt(2)), (1, -1, 1 / math.sqrt(2)))
    diffs = []
    for dy, dx, _ in shifts:
        d = np.zeros((h, w), np.float32)
        ys, ye = 0, h - dy
        xs, xe = max(0, -dx), w - max(0, dx)
        d[ys:ye, xs:xe] = ((img[ys:ye, xs:xe] - img[ys + dy : ye + dy, xs + dx : xe + dx]) ** 2).sum(-1)
        diffs.append((d, ys, ye, xs, xe))
    total = sum(d.sum() for d, *_ in diffs)
    count = sum((ye - ys) * (xe - xs) for _, ys, ye, xs, xe in diffs)
    beta = 0.0 if total <= 0 else 1.0 / (2.0 * total / count)
    g = maxflow.Graph[float]()
    nodes = g.add_grid_nodes((h, w))
    for (dy, dx, k), (d, ys, ye, xs, xe) in zip(shifts, diffs):
        wgt = np.zeros((h, w), np.float64)
        wgt[ys:ye, xs:xe] = gamma * k * np.exp(-beta * d[ys:ye, xs:xe])
        st = np.zeros((3, 3))
        st[1 + dy, 1 + dx] = 1
        g.add_grid_edges(nodes, weights=wgt, structure=st, symmetric=True)
    lo = log_odds.astype(np.float64)
    big = 1e9
    if fixed_bg is not None:
        lo = np.where(fixed_bg, -big, lo)
    if fixed_fg is not None:
        lo = np.where(fixed_fg, big, lo)
    # source = object: a node left on the sink side (background) pays the source edge, max(lo, 0)
    g.add_grid_tedges(nodes, np.maximum(lo, 0), np.maximum(-lo, 0))
    g.maxflow()
    return ~g.get_grid_segments(nodes)
