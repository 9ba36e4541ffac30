"""Checkpoints of a fit: ``<run>/checkpoints/step-<phase index>-<phase>-<step>.pt``, the last
``output.keep_checkpoints`` kept, each written to a temporary name and renamed. A checkpoint of another format
version is refused in one line (its run must be refit). ``--resume`` reads the newest that can be read: a damaged
one (cut short, overwritten, not a checkpoint) is passed over for the one before it, with a warning."""

from __future__ import annotations

import logging
from pathlib import Path

import torch

from s3o_warp.data.io import torch_save
from s3o_warp.errors import InputError

log = logging.getLogger(__name__)

CHECKPOINT_VERSION = 3
"""Format of checkpoints and branch checkpoints, bumped when what they hold or the settings they record change; a
checkpoint of another version is refused (its run must be refit)."""


STATE_KEYS = ("version", "sequence", "num_frames", "phase", "step", "model", "optimizer", "generator", "skeleton",
              "lap_ref", "torch_rng", "config")
"""What every step checkpoint of this format holds (``Fitter.state``)."""


def check_version(state: dict, what: str, fix: str) -> None:
    """InputError, one line naming ``what`` and the ``fix``, unless ``state`` is a checkpoint of this format."""
    v = state.get("version")
    if v != CHECKPOINT_VERSION:
        age = "an earlier" if v is None or (isinstance(v, int) and v < CHECKPOINT_VERSION) else "another"
        raise InputError(f"{what} was written by {age} version of s3o-warp (checkpoint version {v}, this one reads "
                         f"{CHECKPOINT_VERSION}) and must be refit: {fix}")


def save_step(run_dir: Path, state: dict, phase_index: int, phase: str, step: int, keep: int) -> Path:
    """Write ``state`` as the checkpoint of ``phase`` (``phase_index`` orders phases in the name) at ``step`` and
    delete all but the newest ``keep``; returns its path."""
    ck = Path(run_dir) / "checkpoints"
    ck.mkdir(parents=True, exist_ok=True)
    path = ck / f"step-{phase_index}-{phase}-{step:06d}.pt"
    torch_save(state, path)
    kept = sorted(ck.glob("step-*.pt"), key=lambda p: p.stat().st_mtime)
    for old in kept[:-keep]:
        old.unlink(missing_ok=True)
    return path


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The newest step checkpoint of a run, or None."""
    ck = Path(run_dir) / "checkpoints"
    files = sorted(ck.glob("step-*.pt"), key=lambda p: p.name) if ck.is_dir() else []
    return files[-1] if files else None


def load_newest(run_dir: Path, map_location=None) -> tuple[Path, dict] | None:
    """``(path, state)`` of the newest step checkpoint of a run that can be read, or None when it has none.

    One that cannot be read (cut short, not a torch file, not a checkpoint's dict or lacking its keys) is passed
    over for the one before it, with one warning line naming it and why; when none can be read, InputError names
    the folder. A checkpoint of another format version is returned as it is, for :func:`check_version` to refuse.
    """
    ck = Path(run_dir) / "checkpoints"
    files = sorted(ck.glob("step-*.pt"), key=lambda p: p.name, reverse=True) if ck.is_dir() else []
    for path in files:
        try:
            st = torch.load(path, map_location=map_location, weights_only=False)
            missing = [k for k in STATE_KEYS if k not in st] if isinstance(st, dict) else None
        except Exception as e:  # noqa: BLE001 - whatever a damaged file raises, the next older one is tried
            why = f"{type(e).__name__}: {str(e).strip().splitlines()[0] if str(e).strip() else 'no message'}"[:200]
        else:
            if missing is None:
                why = f"it holds a {type(st).__name__}, not a checkpoint"
            elif missing and st.get("version") == CHECKPOINT_VERSION:
                why = f"it lacks {', '.join(missing)}"
            else:
                return path, st
        log.warning("--resume: checkpoint %s cannot be read (%s); trying the one before it", path, why)
    if files:
        raise InputError(f"--resume: none of the {len(files)} checkpoints in {ck} can be read (each is named "
                         "above); fit again without --resume")
    return None
