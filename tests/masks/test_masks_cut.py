"""The graph cut's evidence (s3o_warp.masks.cut): colour mixtures' likelihoods, the motion log-odds on a made-up
two-layer flow field, the shape prior, and the cut itself."""

from __future__ import annotations

import itertools
import math

import cv2
import numpy as np
import pytest

from s3o_warp.masks.cut import (GAMMA, colour_log_odds, fb_error, gmm_log_likelihood, graph_cut, motion_log_odds,
                                shape_log_odds)
from s3o_warp.masks.grabcut import colour_models


def _pixels(mean, n=4000, seed=0, spread=12.0):
    rng = np.random.default_rng(seed)
    return np.clip(rng.normal(mean, spread, (n, 3)), 0, 255).astype(np.uint8)


def test_gmm_log_likelihood_is_the_mixture_density():
    red, green = _pixels([200, 50, 40]), _pixels([90, 140, 80], seed=1)
    bgd, fgd = colour_models(red, green)
    m = fgd.ravel()
    w, mu, cov = m[:5], m[5:20].reshape(5, 3), m[20:65].reshape(5, 3, 3)
    x = red[:50].astype(np.float64)
    want = np.log(sum(
        wk * np.exp(-0.5 * np.einsum("ni,ij,nj->n", x - mk, np.linalg.inv(ck), x - mk))
        / np.sqrt((2 * np.pi) ** 3 * np.linalg.det(ck))
        for wk, mk, ck in zip(w, mu, cov)))
    np.testing.assert_allclose(gmm_log_likelihood(fgd, red[:50]), want, rtol=1e-4, atol=1e-3)
    lo = colour_log_odds(np.concatenate([red[:100], green[:100]])[:, None, :], (bgd, fgd))[:, 0]
    assert (lo[:100] > 0).all() and (lo[100:] < 0).all()


def two_layers(h=96, w=128, obj=(3.0, 1.0), bg=(-2.0, 0.0)):
    """A flow field: the square [30:60, 40:80] moves by ``obj``, the rest by ``bg`` plus a slow zoom (parallax-free
    but not one translation)."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    flow = np.stack([bg[0] + 0.01 * (xx - w / 2), bg[1] + 0.01 * (yy - h / 2)], -1)
    square = np.zeros((h, w), bool)
    square[30:60, 40:80] = True
    flow[square] = obj
    return flow.astype(np.float32), square


def test_motion_log_odds_separates_a_square_moving_otherwise():
    flow, square = two_layers()
    expected = cv2.dilate(square.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # the prior: a little too large
    background = ~(cv2.dilate(square.astype(np.uint8), np.ones((21, 21), np.uint8)) > 0)
    lo = motion_log_odds(flow, expected, background, sigma=8.0)
    inner = cv2.erode(square.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    outer = ~(cv2.dilate(square.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)
    assert (lo[inner] > 1.0).all()  # including the band the prior wrongly holds, the square's edge excepted
    assert (lo[outer] < -0.5).all()


def test_motion_log_odds_says_nothing_where_the_motions_agree_or_the_flow_fails():
    flow, square = two_layers(obj=(-2.0, 0.0))  # the square moves as the background does (near the centre)
    background = ~(cv2.dilate(square.astype(np.uint8), np.ones((21, 21), np.uint8)) > 0)
    lo = motion_log_odds(flow, square, background, sigma=8.0)
    assert np.abs(lo[square]).mean() < 0.5
    flow, square = two_layers()
    bad = np.full(square.shape, 10.0, np.float32)  # forward and backward flow disagree everywhere
    assert np.abs(motion_log_odds(flow, square, background, 8.0, fb=bad)).max() < 1e-6


def test_fb_error_is_zero_for_consistent_flows():
    flow = np.zeros((20, 30, 2), np.float32)
    flow[..., 0] = 2.0
    back = -flow
    assert fb_error(flow, back)[:, :-3].max() < 1e-5
    assert fb_error(flow, flow)[:, :-3].min() > 3.9


def test_shape_log_odds_sign_and_clip():
    prior = np.zeros((40, 40), bool)
    prior[10:30, 10:30] = True
    lo = shape_log_odds(prior, scale=2.0, clip=1.5)
    assert lo[20, 20] == 1.5 and lo[0, 0] == -1.5 and abs(lo[20, 10]) <= 0.5


def _energy(image: np.ndarray, log_odds: np.ndarray, labels: np.ndarray, gamma: float = GAMMA) -> float:
    """The energy graph_cut minimises, written out pair by pair: a pixel labelled background pays its log-odds where
    positive, one labelled object its negative where negative; neighbours (8-connected) labelled apart pay
    gamma / distance x exp(-beta |colour difference|^2), beta = 1 / (2 x the mean squared difference over all
    neighbour pairs)."""
    h, w = log_odds.shape
    img = image.astype(np.float64)
    pairs = []
    for y in range(h):
        for x in range(w):
            for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
                if 0 <= y + dy < h and 0 <= x + dx < w:
                    d = ((img[y, x] - img[y + dy, x + dx]) ** 2).sum()
                    pairs.append((y, x, y + dy, x + dx, math.hypot(dy, dx), d))
    beta = 1.0 / (2.0 * np.mean([p[5] for p in pairs]))
    e = float(np.where(labels, np.maximum(-log_odds, 0), np.maximum(log_odds, 0)).sum())
    for y0, x0, y1, x1, dist, d in pairs:
        if labels[y0, x0] != labels[y1, x1]:
            e += gamma / dist * math.exp(-beta * d)
    return e


def test_graph_cut_is_the_least_energy_labelling():
    """Against every labelling of a 3 x 4 grid (4,096), with evidence on the smoothness's scale so that neither
    wins everywhere; and with pixels fixed, against every labelling that keeps them."""
    rng = np.random.default_rng(1)
    h, w = 3, 4
    every = np.array(list(itertools.product([False, True], repeat=h * w))).reshape(-1, h, w)
    for trial in range(12):
        image = rng.integers(0, 256, (h, w, 3)).astype(np.uint8)
        lo = rng.normal(0, 60, (h, w)).astype(np.float32)
        fixed_bg = fixed_fg = None
        allowed = every
        if trial % 2:
            fixed_bg, fixed_fg = np.zeros((h, w), bool), np.zeros((h, w), bool)
            fixed_bg[0, 0] = fixed_fg[2, 3] = True
            lo[0, 0], lo[2, 3] = 200.0, -200.0  # the evidence says otherwise
            allowed = every[~every[:, 0, 0] & every[:, 2, 3]]
        got = graph_cut(image, lo, fixed_bg=fixed_bg, fixed_fg=fixed_fg)
        best = min(_energy(image, lo, lab) for lab in allowed)
        assert got.shape == (h, w) and got.dtype == bool
        if fixed_bg is not None:
            assert not got[0, 0] and got[2, 3]
        assert _energy(image, lo, got) == pytest.approx(best, rel=1e-9, abs=1e-6)
        assert 0 < got.sum() < h * w or trial % 2 == 0  # not trivially all one label where the fixed pixels differ


def test_graph_cut_smooths_noisy_evidence_and_follows_the_edge_of_colour():
    h, w = 64, 80
    disc = np.zeros((h, w), np.uint8)
    cv2.circle(disc, (40, 32), 16, 1, -1)
    disc = disc.astype(bool)
    image = np.where(disc[..., None], 180, 60).astype(np.uint8).repeat(3, -1)
    rng = np.random.default_rng(0)
    lo = (np.where(disc, 1.0, -1.0) + rng.normal(0, 2.0, (h, w))).astype(np.float32)
    got = graph_cut(image, lo)
    assert (got & disc).sum() / (got | disc).sum() > 0.95
    assert ((lo > 0) ^ disc).sum() > 10 * (got ^ disc).sum()  # the noise alone is far worse
    # evidence for the object spilling 6 pixels past the disc's edge: the cut keeps to the colour edge (free to cut)
    grown = cv2.dilate(disc.astype(np.uint8), np.ones((13, 13), np.uint8)) > 0
    got = graph_cut(image, np.where(grown, 1.0, -1.0).astype(np.float32))
    assert (got ^ disc).sum() == 0
    # on a uniform image, where every cut costs GAMMA a pixel of edge, evidence strong enough to pay for the edge is
    # cut where it changes; the same evidence, weak, is not worth its edge
    uniform = np.full((h, w, 3), 120, np.uint8)
    assert (graph_cut(uniform, np.where(grown, 20.0, -20.0).astype(np.float32)) ^ grown).sum() == 0
    assert not graph_cut(uniform, np.where(grown, 1.0, -1.0).astype(np.float32)).any()
