"""What a user sees for awkward input: several blobs, an object leaving the frame, bad CLI input."""

from __future__ import annotations

import logging
import os

import cv2
import numpy as np
import pytest

from s3o_warp.cli import main as cli_main
from s3o_warp.config import DataConfig
from s3o_warp.data.sequence import open_sequence


def _write_seq(root, masks, size=(48, 64)):
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    rng = np.random.default_rng(0)
    for k, m in enumerate(masks):
        img = (rng.random(size + (3,)) * 255).astype(np.uint8)
        cv2.imwrite(str(root / "images" / f"{k:05d}.png"), img)
        cv2.imwrite(str(root / "masks" / f"{k:05d}.png"), m.astype(np.uint8) * 255)
    return root


def _blob(size=(48, 64), box=(10, 10, 30, 40)):
    m = np.zeros(size, bool)
    y0, x0, y1, x1 = box
    m[y0:y1, x0:x1] = True
    return m


def test_several_blobs_use_the_largest_with_a_warning(tmp_path, caplog):
    two = _blob() | _blob(box=(40, 55, 44, 60))
    seq_dir = _write_seq(tmp_path / "seq", [two, _blob(), _blob()])
    with caplog.at_level(logging.WARNING):
        seq = open_sequence(seq_dir, cfg=DataConfig())
    assert any("disconnected blobs" in r.getMessage() and "00000.png" in r.getMessage() for r in caplog.records)
    assert seq.mask(0).sum() == _blob().sum()
    assert tuple(seq.bboxes[0]) == tuple(seq.bboxes[1])
    keep_all = open_sequence(seq_dir, cfg=DataConfig(largest_blob=False))
    assert keep_all.mask(0).sum() == two.sum()


def test_fragments_next_to_the_object_are_kept(tmp_path):
    body = _blob(box=(10, 10, 30, 40))
    leg = _blob(box=(31, 20, 38, 22))  # broke off one pixel below the body
    seq = open_sequence(_write_seq(tmp_path / "seq", [body | leg, body, body]), cfg=DataConfig())
    assert seq.mask(0).sum() == body.sum() + leg.sum()


def test_object_leaving_the_frame_is_down_weighted_with_a_warning(tmp_path, caplog):
    seq_dir = _write_seq(tmp_path / "seq", [_blob(), _blob(box=(10, 30, 30, 64)), _blob()])
    with caplog.at_level(logging.WARNING):
        seq = open_sequence(seq_dir, cfg=DataConfig())
    assert list(seq.touches_border) == [False, True, False]
    assert any("touches the frame border in 1 frame" in r.getMessage() for r in caplog.records)

    import torch

    from s3o_warp.motion.losses import silhouette_loss

    sil = torch.zeros(3, 4, 4)
    mask = torch.zeros(3, 4, 4)
    mask[1] = 1  # only the border frame is wrong
    w = torch.tensor([1.0, 0.3, 1.0])
    assert silhouette_loss(sil, mask, w) == pytest.approx(0.3 / 2.3)
    assert silhouette_loss(sil, mask) == pytest.approx(1 / 3)


def test_cli_bad_input_is_one_line_and_exit_code_2(tmp_path, capsys):
    assert cli_main([str(tmp_path / "missing"), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not exist" in err[0]

    seq_dir = _write_seq(tmp_path / "seq", [_blob(), _blob()])
    assert cli_main([str(seq_dir), "--out", str(tmp_path / "r2"), "--set", "motion.stepz=3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "motion.stepz" in err[0]

    cfg = tmp_path / "bad.toml"
    cfg.write_text("[motion]\nsteps = 'x'\n")
    assert cli_main([str(seq_dir), "--out", str(tmp_path / "r3"), "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'motion.steps' must be int" in err[0]
    assert not (tmp_path / "r2").exists() and not (tmp_path / "r3").exists()

    assert cli_main([str(seq_dir), "--out", str(tmp_path / "r5"), "--branch-from", str(tmp_path / "nofit")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--branch-from" in err[0] and "checkpoints/branch.pt" in err[0]
    assert not (tmp_path / "r5").exists()

    empty = _write_seq(tmp_path / "seq_empty", [_blob(), np.zeros((48, 64), bool)])
    assert cli_main([str(empty), "--out", str(tmp_path / "r4")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "00001.png" in err[0] and "empty" in err[0]


def test_unwritable_run_directory_is_refused_before_anything_is_written(tmp_path, capsys, monkeypatch):
    import s3o_warp.fit as fit_mod

    seq_dir = _write_seq(tmp_path / "seq", [_blob(), _blob()])
    ro = tmp_path / "ro"
    ro.mkdir()
    real_access = os.access
    monkeypatch.setattr(fit_mod.os, "access", lambda p, mode: False if str(p) == str(ro) else real_access(p, mode))
    assert cli_main([str(seq_dir), "--out", str(ro / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not writable" in err[0]
    assert not (ro / "run").exists()
