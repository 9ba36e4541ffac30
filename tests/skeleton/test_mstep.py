"""The M-step module's own functions (s3o_warp.skeleton.mstep); the schedule itself is tested through the fit."""

from __future__ import annotations

import numpy as np

from s3o_warp.skeleton.edit import DEFAULT_SHARPNESS
from s3o_warp.skeleton.mstep import virtual_bones

# -------------------------------------------------------------------------------------------------
# LASR-like baseline
# -------------------------------------------------------------------------------------------------


def test_virtual_bones_deterministic_with_seed():
    rng = np.random.default_rng(10)
    X = rng.normal(size=(500, 3)) * [3, 1, 1]
    c1, q1 = virtual_bones(X, 8, seed=3)
    c2, q2 = virtual_bones(X, 8, seed=3)
    c3, _ = virtual_bones(X, 8, seed=4)
    np.testing.assert_array_equal(c1, c2)
    np.testing.assert_array_equal(q1, q2)
    assert not np.allclose(np.sort(c1[:, 0]), np.sort(c3[:, 0]))
    assert c1.shape == (8, 3) and q1.shape == (8, 3, 3)
    off = q1 - np.eye(3) * q1[:, :1, :1]
    assert np.abs(off).max() == 0 and (q1[:, 0, 0] > 0).all()  # isotropic, positive
    lab = np.argmin(((X[:, None] - c1[None]) ** 2).sum(-1), 1)
    var = np.array([((X[lab == b] - c1[b]) ** 2).sum(1).mean() / 3 for b in range(8)])
    np.testing.assert_allclose(q1[:, 0, 0], DEFAULT_SHARPNESS / var, rtol=1e-6)
