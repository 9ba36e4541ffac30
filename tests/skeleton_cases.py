"""Hand-made skeleton cases shared by the tests of s3o_warp.skeleton: point clouds along segments, hard
weights, a three-bone chain and flow fields."""

from __future__ import annotations

import numpy as np


def segment_cloud(a, b, n, radius, rng):
    """n points in a cylinder of ``radius`` around the segment a -> b (x-aligned segments here)."""
    t = rng.uniform(0, 1, n)
    a, b = np.asarray(a, float), np.asarray(b, float)
    p = a + t[:, None] * (b - a)
    return p + rng.normal(0, radius, (n, 3)) * np.array([0.2, 1, 1])


def hard_weights(labels, B, soft=0.0):
    W = np.full((len(labels), B), soft / max(B - 1, 1))
    W[np.arange(len(labels)), labels] = 1 - soft
    return W


def chain(n_per=60, seed=0):
    """Three segments along x: [0,1], [1,2], [2,3]; weights blend linearly across the joints at 1 and 2."""
    rng = np.random.default_rng(seed)
    X = np.concatenate([segment_cloud([i, 0, 0], [i + 1, 0, 0], n_per, 0.05, rng) for i in range(3)])
    x = X[:, 0]
    W = np.zeros((len(X), 3))
    for b in range(3):  # hat functions centred at 0.5, 1.5, 2.5 with support of 1 each side
        W[:, b] = np.clip(1 - np.abs(x - (b + 0.5)), 0, 1)
    W[x < 0.5, 0] = 1
    W[x > 2.5, 2] = 1
    W /= W.sum(1, keepdims=True)
    return X, W


def flow_field(T1, S, fn):
    """(T1, S, S, 2) float32 flow from fn(col, row, t) -> (dx, dy), pixel centres at integers."""
    c, r = np.meshgrid(np.arange(S, dtype=np.float64), np.arange(S, dtype=np.float64))
    return np.stack([np.stack(fn(c, r, t), -1) for t in range(T1)]).astype(np.float32)
