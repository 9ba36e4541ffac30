"""A fit branched from another run of the same sequence at another skeleton granularity (``--branch-from``).

Everything before the first M-step that reads ``skeleton.t_o`` (the first merge, after epoch e1 + 1 of the joint
phase) is the same for every t_o, so a fit writes ``checkpoints/branch.pt`` there, with that M-step pending, and
``checkpoints/branch.log.jsonl`` (its log so far). A branched fit starts from them and from the parent's cached
flow; it may differ from the parent only in the settings read from there on (:data:`BRANCH_MAY_DIFFER`).
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import torch

from s3o_warp.config import Config, to_dict
from s3o_warp.data.io import copy_file, torch_save
from s3o_warp.errors import InputError
from s3o_warp.run.checkpoint import check_version

log = logging.getLogger(__name__)

BRANCH_CHECKPOINT = "branch.pt"  # in <run>/checkpoints: the state before the first M-step that reads t_o
BRANCH_LOG = "branch.log.jsonl"
BRANCH_MAY_DIFFER = ("skeleton.t_o", "skeleton.t_u", "skeleton.t_d")
"""The settings a branched fit may change: the refinement reads them only after the branch (and output.*, preset:
no effect on the fit)."""


def save_branch(run_dir: Path, state: dict, log_file: Path) -> Path:
    """``checkpoints/branch.pt`` (``state``, its M-step marked pending) and ``checkpoints/branch.log.jsonl``."""
    ck = Path(run_dir) / "checkpoints"
    ck.mkdir(parents=True, exist_ok=True)
    path = ck / BRANCH_CHECKPOINT
    torch_save({**state, "pending_m_step": True}, path)
    copy_file(log_file, ck / BRANCH_LOG)
    return path


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def branch_checkpoint(parent: Path, out_dir: Path, cfg: Config) -> Path:
    """The branch checkpoint of run ``parent`` for a fit with ``cfg`` into ``out_dir``; InputError when it is
    missing or the settings differ in more than :data:`BRANCH_MAY_DIFFER`."""
    ck = parent / "checkpoints" / BRANCH_CHECKPOINT
    if parent.resolve() == out_dir.resolve():
        raise InputError(f"--branch-from {parent}: that is the run directory itself; choose another --out")
    if not ck.is_file():
        raise InputError(f"--branch-from {parent}: no {ck.relative_to(parent)} there (it is written just before the "
                         "first merge of a fit with skeleton.method=s3o, skeleton.epochs >= skeleton.e1 + 3 and "
                         "output.branch_checkpoint=true); fit that run first or drop --branch-from")
    st = torch.load(ck, map_location="cpu", weights_only=False)
    check_version(st, f"--branch-from {parent}: its {ck.relative_to(parent)}", "refit that run, then branch from it")
    theirs = _flat(st["config"])
    ours = _flat(to_dict(cfg))
    free = set(BRANCH_MAY_DIFFER) | {"preset"}
    differ = sorted(k for k in set(theirs) | set(ours)
                    if k not in free and not k.startswith("output.") and theirs.get(k) != ours.get(k))
    if differ:
        shown = ", ".join(f"{k} ({theirs.get(k)!r} there, {ours.get(k)!r} here)" for k in differ[:4])
        raise InputError(f"--branch-from {parent}: its settings differ in {shown}{' ...' if len(differ) > 4 else ''}; "
                         f"only {', '.join(BRANCH_MAY_DIFFER)} may differ, fit afresh for the others")
    return ck


def link_cache(src: Path, dst: Path) -> None:
    """The parent run's cached flow for a branched fit: hard links (a copy across file systems). The flow files
    are written once under a temporary name and renamed, so neither run ever writes into the other's; the crops'
    memory map (long sequences) is rewritten by each run and not shared."""
    if not src.is_dir():
        return
    for f in src.glob("flow_*.npy"):
        t = dst / f.name
        if t.exists():
            continue
        t.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(f, t)
        except OSError:
            shutil.copy2(f, t)


