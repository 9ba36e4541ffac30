"""Where a benchmark number came from: versions, git commit and device name (for benchmarks/*.json)."""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path

import numpy
import torch
import warp

REPO = Path(__file__).resolve().parents[1]


def versions() -> dict:
    """Python, torch, Warp and numpy versions."""
    return {"python": platform.python_version(), "torch": torch.__version__, "warp": warp.config.version, "numpy": numpy.__version__}


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo`` on Linux), else what ``platform`` knows. CPU fits are chaotic, so
    one commit and seed can end elsewhere on another CPU: benchmark rows say which one they ran on."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


CODE_PATHS = ("s3o_warp", "scripts", "kernels", "pyproject.toml")
"""What a benchmark row's code is: uncommitted changes here make its commit ``<sha>-dirty``."""


def git_commit() -> str | None:
    """The checkout's HEAD commit, with ``-dirty`` when the code (``CODE_PATHS``) differs from it; None outside
    a git checkout. A row measured on uncommitted code must not carry the commit's name alone.

    ``S3O_GIT_COMMIT``, when set, names the commit instead: a copy of the tree sent to another machine (a lent
    GPU) may carry no ``.git``, or a stale one whose HEAD is not the code that runs."""
    if os.environ.get("S3O_GIT_COMMIT"):
        return os.environ["S3O_GIT_COMMIT"]
    try:
        sha = subprocess.check_output(["git", "rev-parse", "HEAD"], cwd=REPO, text=True, stderr=subprocess.DEVNULL).strip()
    except Exception:
        return None
    try:
        clean = subprocess.run(["git", "diff", "--quiet", "HEAD", "--", *CODE_PATHS], cwd=REPO,
                               stderr=subprocess.DEVNULL).returncode == 0
    except Exception:
        clean = True
    return sha if clean else f"{sha}-dirty"


def device_name(device: str) -> str:
    """The GPU's name for ``cuda[:N]``, else the CPU's (with the core count)."""
    if str(device).startswith("cuda"):
        return torch.cuda.get_device_name(device)
    return f"{platform.processor() or platform.machine()} ({os.cpu_count()} cores)"
