"""Atomic file output: every file of a run is written to a temporary name beside it, then renamed onto it, so a
crash or a stop never leaves a half-written file where a finished one is expected; and the JSON reader whose
errors name the file and the fix (:func:`read_json`)."""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

import torch

from s3o_warp.errors import InputError


@contextlib.contextmanager
def atomic_path(path):
    """A temporary path beside ``path`` (same suffix, so writers that choose the format by it still work); when the
    block ends without an error it is renamed onto ``path``, otherwise removed.

    Concretely, ``with atomic_path("a/b.png") as tmp: imageio.imwrite(tmp, img)`` writes ``a/.b.<pid>.tmp.png``
    and renames it to ``a/b.png``.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes(path, data: bytes) -> Path:
    """``path`` holds ``data``, written atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text(path, text: str) -> Path:
    """``path`` holds ``text`` (UTF-8), written atomically."""
    return write_bytes(path, text.encode())


def write_json(path, obj, indent: int | None = 2) -> Path:
    """``path`` holds ``obj`` as JSON, written atomically; its folder is made when missing."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return write_text(path, json.dumps(obj, indent=indent) + "\n")


def read_json(path, what: str, fix: str):
    """Parse a JSON file; a missing or malformed file raises a one-line ``InputError`` with ``fix``."""
    path = Path(path)
    try:
        with open(path) as f:
            return json.load(f)
    except FileNotFoundError:
        raise InputError(f"{path}: {what} not found; {fix}") from None
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: not valid JSON ({e.msg} at line {e.lineno}); {fix}") from None


def copy_file(src, dst) -> Path:
    """``dst`` becomes a copy of ``src`` (empty when ``src`` is missing), written atomically."""
    src = Path(src)
    return write_bytes(dst, src.read_bytes() if src.is_file() else b"")


def torch_save(obj, path) -> Path:
    """``torch.save(obj, path)``, written atomically."""
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)
    return Path(path)
