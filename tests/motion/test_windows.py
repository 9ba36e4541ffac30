"""The warm-up's sweep of frame windows (motion/windows.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import smoke_config

from s3o_warp.coarse.model import coarse_model
from s3o_warp.data.store import prepare_data
from s3o_warp.fit import Fitter
from s3o_warp.motion.windows import seed_unvisited

_cfg = smoke_config  # tiny_sequence: conftest.py


def test_sweep_seeds_new_frames_from_the_nearest_visited_one(tiny_sequence, tmp_path):
    cfg = _cfg(**{"coarse.steps": 2})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    m = f.model
    m.visited.zero_()
    m.visited[[2, 3]] = True
    g = torch.Generator().manual_seed(0)
    params = (m.root_aa, m.root_t, m.bone_aa, m.bone_t)
    with torch.no_grad():
        for p in params:
            p.data[2] = torch.randn(p.shape[1:], generator=g)
            p.data[3] = torch.randn(p.shape[1:], generator=g)
    seed_unvisited(m, torch.arange(2, 7), f.coarse.canonical)  # 4, 5, 6 are new, 3 their nearest visited frame
    for p in params:
        assert not torch.equal(p.data[2], p.data[3])
        for fr in (4, 5, 6):
            torch.testing.assert_close(p.data[fr], p.data[3], rtol=0, atol=0)
    assert m.visited[2:7].all()


@pytest.mark.parametrize("stride", [0, 1, 3])
def test_sweep_moves_outward_by_its_stride(tiny_sequence, tmp_path, stride):
    cfg = _cfg(**{"coarse.steps": 2, "motion.batch_frames": 4})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    T, n, c = data.num_frames, 4, f.coarse.canonical
    starts = f.windows.sweep_starts(stride)
    s0 = min(max(c - n // 2, 0), T - n)
    assert starts[0] == s0 and 0 in starts and T - n in starts and len(set(starts)) == len(starts)
    step = stride or n // 2
    right = [s for s in starts if s > s0]
    left = [s for s in starts if s < s0]
    assert right == sorted(right) and left == sorted(left, reverse=True)  # outward on each side
    for side in (right, left):  # consecutive stages move by the stride (the last may be shorter, to reach the end)
        gaps = np.abs(np.diff([s0] + side))
        assert (gaps[:-1] == step).all() and 0 < gaps[-1] <= step if len(gaps) else True
