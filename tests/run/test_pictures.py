"""The canonical pictures: side, top and front show the object's three extents; the grey row is the same shape."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import trimesh

from s3o_warp.run.pictures import canonical_views


def _extent(img: np.ndarray) -> tuple[int, int]:
    fg = np.abs(img.astype(int) - img[0, 0].astype(int)).sum(-1) > 30  # not the background
    rows, cols = np.flatnonzero(fg.any(1)), np.flatnonzero(fg.any(0))
    return rows[-1] - rows[0] + 1, cols[-1] - cols[0] + 1


def test_canonical_views_show_length_height_and_width(tmp_path):
    m = trimesh.creation.icosphere(3)
    v = (m.vertices * [2.0, 1.0, 0.5]).astype(np.float32)  # length x, height y (down), width z
    rig = SimpleNamespace(verts=v, faces=m.faces.astype(np.int32), colors=np.full((len(v), 3), 0.6, np.float32),
                          weights=np.ones((len(v), 1), np.float32), centres=None, joints=None, joint_pairs=None)
    (tmp_path / "renders").mkdir()
    paths = canonical_views(tmp_path, rig, turntable_frames=4)
    names = sorted(p.name for p in paths)
    assert names[:4] == ["bones.png", "canonical_front.png", "canonical_side.png", "canonical_top.png"]
    grid = cv2.imread(str(tmp_path / "renders" / "canonical_views.png"))
    assert grid.shape == (512, 768, 3)
    ratios = []
    for k in range(3):  # each view is scaled to fit: compare its two extents
        h, w = _extent(grid[:256, 256 * k:256 * (k + 1)])
        hg, wg = _extent(grid[256:, 256 * k:256 * (k + 1)])
        assert abs(h - hg) <= 2 and abs(w - wg) <= 2  # the grey row is the same shape
        ratios.append(min(h, w) / max(h, w))
    side, top, front = ratios  # side: height / length 0.5; top: width / length 0.25; front: width / height 0.5
    assert abs(side - 0.5) < 0.06 and abs(top - 0.25) < 0.05 and abs(front - 0.5) < 0.06
