"""data.io.write_video: an mp4 from a list or a stream of frames, read back frame for frame."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from s3o_warp.data.io import write_video


@pytest.mark.parametrize("as_stream", [False, True])
def test_write_video_keeps_every_frame(tmp_path, as_stream):
    frames = [np.full((48, 64, 3), 40 * k, np.uint8) for k in range(5)]
    path = write_video(iter(frames) if as_stream else frames, tmp_path / "v.mp4", fps=10)
    if path.suffix == ".gif":  # OpenCV without an mp4 encoder
        pytest.skip("no mp4 encoder in this OpenCV")
    cap = cv2.VideoCapture(str(path))
    got = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        got.append(f)
    assert len(got) == len(frames) and got[0].shape == (48, 64, 3)
    assert [int(round(f.mean())) for f in got] == pytest.approx([40 * k for k in range(5)], abs=3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]  # no temporary left
