"""Files in and out. Output is atomic: every file (or folder) is written under a temporary name beside it, then
renamed onto it, so a crash or a stop never leaves a half-written file where a finished one is expected. JSON is
read by :func:`read_json`, whose errors name the file and the fix.

Temporary names are ``.NAME.tmp-PID.EXT`` (files) and ``.NAME.tmp-PID`` (folders). An exception removes its own
temporary; a killed process leaves it behind, and the next write of the same path removes it.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import os
import re
import shutil
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np
import torch
from PIL import Image

from s3o_warp.errors import InputError

log = logging.getLogger(__name__)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _temp_name(path: Path) -> Path:
    """``.NAME.tmp-PID.EXT`` beside ``path`` (same suffix, so writers that choose the format by it still work)."""
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")


def _remove_stale_temps(path: Path) -> None:
    """Remove temporaries of ``path`` left by processes that no longer run (killed writers)."""
    pattern = re.compile(rf"^\.{re.escape(path.stem)}\.tmp-(\d+){re.escape(path.suffix)}$")
    for p in path.parent.iterdir():
        m = pattern.match(p.name)
        if m and int(m.group(1)) != os.getpid() and not _pid_alive(int(m.group(1))):
            log.info("removing %s, left by a writer that was killed", p)
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    p.unlink()


def _temp_beside(path) -> Path:
    path = Path(path)
    if not path.parent.is_dir():
        raise InputError(f"{path}: the output folder {path.parent} does not exist; create it or choose another path")
    _remove_stale_temps(path)
    return _temp_name(path)


@contextlib.contextmanager
def atomic_path(path) -> Iterator[Path]:
    """A temporary path beside ``path``; when the block ends without an error it is renamed onto ``path``, otherwise
    removed.

    Concretely, ``with atomic_path("a/b.png") as tmp: cv2.imwrite(str(tmp), img)`` writes ``a/.b.tmp-<pid>.png``
    and renames it to ``a/b.png``. The folder ``a`` must exist (:class:`InputError` otherwise).
    """
    tmp = _temp_beside(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


@contextlib.contextmanager
def atomic_dir(path) -> Iterator[Path]:
    """A new empty folder beside ``path``; when the block ends without an error it replaces ``path`` (an existing
    folder there is removed), otherwise it is removed. The parent of ``path`` is created if missing."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_beside(path)
    tmp.mkdir()
    try:
        yield tmp
        if path.exists():
            old = path.with_name(f".{path.name}.old-{os.getpid()}")
            path.rename(old)
            tmp.rename(path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def read_json(path, what: str, fix: str):
    """Parse a JSON file; a missing or malformed file raises a one-line :class:`InputError` naming ``what`` and
    ``fix``."""
    path = Path(path)
    try:
        with open(path) as f:
            return json.load(f)
    except FileNotFoundError:
        raise InputError(f"{path}: {what} not found; {fix}") from None
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: not valid JSON ({e.msg} at line {e.lineno}); {fix}") from None


def write_stream(path, writer: Callable[[BinaryIO], object]) -> Path:
    """``path`` holds what ``writer(file)`` writes into a binary file, written atomically (flushed and synced to disk
    before the rename)."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            writer(f)
            f.flush()
            os.fsync(f.fileno())
    return Path(path)


def write_bytes(path, data: bytes) -> Path:
    """``path`` holds ``data``, written atomically."""
    return write_stream(path, lambda f: f.write(data))


def write_text(path, text: str) -> Path:
    """``path`` holds ``text`` (UTF-8), written atomically."""
    return write_bytes(path, text.encode())


def write_json(path, obj, indent: int | None = 2) -> Path:
    """``path`` holds ``obj`` as JSON, written atomically; its folder is made when missing."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return write_text(path, json.dumps(obj, indent=indent) + "\n")


def imwrite(path, image: np.ndarray, name=None) -> Path:
    """Write ``image`` (``(H, W, 3)`` uint8 RGB or ``(H, W)`` grey) to ``path`` as it stands, in the format its suffix
    names (PNG, JPEG...): for files inside a folder that :func:`atomic_dir` renames into place as a whole.
    ``name``: the path an error names (default ``path``)."""
    img = np.ascontiguousarray(image[..., ::-1] if image.ndim == 3 else image)
    if not cv2.imwrite(str(path), img):
        raise InputError(f"{name or path}: could not write the image; check the folder is writable")
    return Path(path)


def write_image(path, image: np.ndarray) -> Path:
    """``path`` holds ``image`` (as :func:`imwrite` takes it), written atomically."""
    with atomic_path(path) as tmp:
        imwrite(tmp, image, name=path)
    return Path(path)


def copy_file(src, dst) -> Path:
    """``dst`` becomes a copy of ``src`` (empty when ``src`` is missing), written atomically."""
    src = Path(src)
    return write_bytes(dst, src.read_bytes() if src.is_file() else b"")


def torch_save(obj, path) -> Path:
    """``torch.save(obj, path)``, written atomically."""
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)
    return Path(path)


class _NoMp4(Exception):
    """OpenCV cannot encode mp4 here: the GIF fallback is written instead."""


def write_video(frames: Iterable[np.ndarray], path, fps: float) -> Path:
    """``frames`` (``(H, W, 3)`` uint8 RGB, one size) as an mp4 (OpenCV, mp4v) streamed frame by frame, or a GIF
    (Pillow) beside it where OpenCV cannot encode mp4; written atomically. Returns the path written.

    A list of frames falls back to the GIF even when OpenCV opens the file but writes nothing; a generator is
    streamed, so only an encoder that refuses to open falls back (its frames are then gathered for the GIF)."""
    path = Path(path)
    it = iter(frames)
    first = next(it)
    h, w = first.shape[:2]
    try:
        with atomic_path(path) as tmp:
            vw = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
            if not vw.isOpened():
                raise _NoMp4
            for f in itertools.chain([first], it):
                vw.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
            vw.release()
            if not (tmp.exists() and tmp.stat().st_size > 0):
                if not isinstance(frames, list):
                    raise InputError(f"{path}: OpenCV wrote an empty video; check the folder is writable")
                raise _NoMp4
        return path
    except _NoMp4:
        pass
    rest = frames[1:] if isinstance(frames, list) else list(it)
    ims = [Image.fromarray(f) for f in [first, *rest]]
    gif = path.with_suffix(".gif")
    with atomic_path(gif) as tmp:
        ims[0].save(tmp, save_all=True, append_images=ims[1:], duration=int(1000 / fps), loop=0)
    return gif
