"""Checkpoints of a fit: ``<run>/checkpoints/step-<phase index>-<phase>-<step>.pt``, the last
``output.keep_checkpoints`` kept, each written to a temporary name and renamed. A checkpoint of another format
version is refused in one line (its run must be refit)."""

from __future__ import annotations

from pathlib import Path

from s3o_warp.data.io import torch_save
from s3o_warp.errors import InputError

CHECKPOINT_VERSION = 3
"""Format of checkpoints and branch checkpoints, bumped when what they hold or the settings they record change; a
checkpoint of another version is refused (its run must be refit)."""


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
