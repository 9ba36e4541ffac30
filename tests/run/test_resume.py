"""``--resume``: the newest checkpoint that can be read (s3o_warp/run/checkpoint.py ``load_newest``) and the settings
changed since it, applied or refused by name before any work (s3o_warp/run/resume.py)."""

from __future__ import annotations

import json
import logging

import pytest
import torch
from conftest import smoke_config, stop_in_joint_phase

import s3o_warp.fit as fit_module
from s3o_warp.config import Config, _settings, make_config, to_dict
from s3o_warp.errors import InputError
from s3o_warp.fit import fit
from s3o_warp.run.checkpoint import CHECKPOINT_VERSION, STATE_KEYS, load_newest
from s3o_warp.run.resume import READ_UNTIL, apply_changed_settings

_cfg = smoke_config


def _state(cfg, phase="joint", step=3, **extra) -> dict:
    return {"version": CHECKPOINT_VERSION, "phase": phase, "step": step, "config": to_dict(cfg), **extra}


def test_every_setting_says_until_when_a_change_takes_effect():
    assert set(READ_UNTIL) == {k for k, *_ in _settings(Config())}


@pytest.mark.parametrize("key, value, phase, step, search, applied", [
    ("motion.steps", 9, "joint", 3, False, True),  # the loop reads its step count at every step
    ("motion.w_flow", 0.5, "warmup", 2, False, True),
    ("skeleton.t_o", 0.9, "joint", 3, False, True),
    ("coarse.steps", 9, "coarse", 3, False, True),
    ("coarse.steps", 9, "warmup", 0, False, False),  # the coarse phase is over
    ("motion.hypotheses", 3, "warmup", 0, False, True),  # the search has not begun
    ("motion.hypotheses", 3, "warmup", 0, True, False),  # inside the search
    ("motion.turn_rate", 2.0, "joint", 1, False, False),
    ("motion.warmup_steps", 9, "warmup", 4, False, True),
    ("motion.warmup_steps", 9, "joint", 0, False, False),
    ("motion.shape_smoothing", 1.0, "joint", 3, False, True),  # the optimiser is made again on resume
    ("data.crop_size", 96, "coarse", 1, False, False),  # read before the first checkpoint
    ("seed", 3, "coarse", 1, False, False),
    ("output.render_video", False, "done", 0, False, True),
    ("skeleton.t_o", 0.9, "done", 0, False, False),  # the fit is done
])
def test_a_changed_setting_is_applied_and_logged_or_refused_by_name(key, value, phase, step, search, applied,
                                                                     tmp_path, caplog):
    saved = make_config("smoke")
    cfg = make_config("smoke", overrides=[f"{key}={value}"])
    old = dict((k, getattr(o, n)) for k, o, n, _ in _settings(saved))[key]
    state = _state(saved, phase, step, **({"hypotheses": {}} if search else {}))
    path = tmp_path / "step.pt"
    if applied:
        with caplog.at_level(logging.INFO, logger="s3o_warp.run.resume"):
            assert apply_changed_settings(state, cfg, path) == [key]
        assert f"applied from there on: {key} {old} -> {value}".lower() in caplog.text.lower()
    else:
        with pytest.raises(InputError) as e:
            apply_changed_settings(state, cfg, path)
        msg = str(e.value)
        shown = "none" if old is None else str(old)
        assert "\n" not in msg and f"written with {key}={shown}," in msg and f"add --set {key}={shown} " in msg
        assert "without --resume" in msg and f"{key} is read only {'until the fit ends' if phase == 'done' else ''}" in msg
    assert apply_changed_settings(state, saved, path) == []  # nothing changed: nothing to say


def test_the_newest_checkpoint_that_can_be_read_is_taken_and_each_damaged_one_named(tmp_path, caplog):
    ck = tmp_path / "checkpoints"
    ck.mkdir()
    assert load_newest(tmp_path) is None
    good = {k: 0 for k in STATE_KEYS} | {"version": CHECKPOINT_VERSION}
    torch.save(good, ck / "step-0-coarse-000004.pt")
    torch.save({**good, "step": 1}, ck / "step-1-warmup-000000.pt")
    (ck / "step-2-joint-000003.pt").write_bytes((ck / "step-0-coarse-000004.pt").read_bytes()[:100])  # cut short
    torch.save([1, 2], ck / "step-2-joint-000004.pt")  # not a checkpoint
    torch.save({k: v for k, v in good.items() if k != "optimizer"}, ck / "step-2-joint-000006.pt")  # lacks a key
    with caplog.at_level(logging.WARNING, logger="s3o_warp.run.checkpoint"):
        path, st = load_newest(tmp_path)
    assert path.name == "step-1-warmup-000000.pt" and st["step"] == 1  # read once, returned
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 3
    assert "step-2-joint-000006.pt cannot be read (it lacks optimizer)" in lines[0]
    assert "step-2-joint-000004.pt cannot be read (it holds a list, not a checkpoint)" in lines[1]
    assert "step-2-joint-000003.pt cannot be read (" in lines[2]
    torch.save({"version": CHECKPOINT_VERSION - 1}, ck / "step-3-done-000000.pt")  # an older format: returned,
    assert load_newest(tmp_path)[0].name == "step-3-done-000000.pt"  # for check_version to refuse in one line
    for p in ck.glob("step-*.pt"):
        p.write_bytes(b"")
    with pytest.raises(InputError, match=rf"^--resume: none of the 6 checkpoints in {ck} can be read .*; fit "
                                         r"again without --resume$"):
        load_newest(tmp_path)


def test_resume_passes_a_damaged_checkpoint_over_applies_a_new_step_count_and_refuses_before_any_work(
        tiny_sequence, tmp_path, monkeypatch, caplog, capsys):
    from s3o_warp.cli import main as cli_main

    over = {"coarse.steps": 2, "motion.warmup_steps": 2, "motion.steps": 6, "skeleton.epochs": 1}  # no M-step
    run = tmp_path / "run"
    stop_in_joint_phase(monkeypatch, tiny_sequence, run, _cfg(**over), match="stopped at joint step 3")
    ck = run / "checkpoints"
    assert sorted(p.name for p in ck.glob("step-*.pt")) == ["step-2-joint-000000.pt", "step-2-joint-000003.pt"]

    # a setting read only before the checkpoint: refused by name before the sequence is read
    def no_work(*args, **kwargs):
        raise AssertionError("the sequence was read")

    with monkeypatch.context() as m:
        m.setattr(fit_module, "prepare_data", no_work)
        with pytest.raises(InputError, match=r"\(joint step 3\) was written with coarse.steps=2, motion.warmup_steps="
                                             r"2, .*add --set coarse.steps=2 --set motion.warmup_steps=2 to continue"):
            fit(tiny_sequence, run, _cfg(**{**over, "coarse.steps": 3, "motion.warmup_steps": 3}), torch.device("cpu"),
                resume=True)

    # the newest is damaged: the one before it (the joint phase's start) is taken; motion.steps 6 -> 8 applies
    (ck / "step-2-joint-000003.pt").write_bytes(b"PK\x03\x04 cut short")
    with caplog.at_level(logging.INFO):
        fit(tiny_sequence, run, _cfg(**{**over, "motion.steps": 8}), torch.device("cpu"), resume=True)
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and "cannot be read" in
              r.getMessage()]
    assert len(warned) == 1 and "step-2-joint-000003.pt" in warned[0]
    assert f"resuming from {ck / 'step-2-joint-000000.pt'}" in caplog.text
    assert "motion.steps 6 -> 8" in caplog.text
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert max(r["step"] for r in log if r["phase"] == "joint") == 8

    # none can be read: one line names the folder (exit 2)
    for p in ck.glob("step-*.pt"):
        p.write_bytes(b"")
    capsys.readouterr()
    rc = cli_main([str(tiny_sequence), "--out", str(run), "--device", "cpu", "--preset", "smoke", "--resume",
                   *[f"--set={k}={v}" for k, v in {**over, "data.crop_size": 64, "motion.batch_frames": 4}.items()]])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert str(ck) in err[0] and err[0].endswith("fit again without --resume")
