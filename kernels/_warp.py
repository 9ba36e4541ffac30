"""Shared Warp plumbing for every kernel family: lazy init, torch <-> Warp views, streams.

Nothing here knows about skeletons or videos. Every torch-facing op goes through these helpers so
that Warp is initialised once, arrays are zero-copy views with ``requires_grad=False`` (we own the
adjoint buffers), and launches run on the current torch stream of the inputs' device.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor

import torch
import warp as wp

_init_lock = threading.Lock()
_initialised = False

NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"
"""What Warp's native library prints to stderr at ``wp.init()`` on a machine without CUDA."""
driver_warning: str | None = None
"""That line, held back by :func:`init` (nothing a CPU user can act on); whoever asks for CUDA shows it."""


def init() -> None:
    """Initialise Warp once (quietly: no banner, and no missing-driver line, kept in :data:`driver_warning`);
    later calls are free."""
    global _initialised, driver_warning
    if _initialised:
        return
    with _init_lock:
        if not _initialised:
            import logging

            # Warp >= 1.19 logs its banner and "Module ... load" lines at INFO; keep warnings only.
            wp.config.log_level = max(wp.config.log_level, logging.WARNING)
            driver_warning = holding_back(wp.init, NO_DRIVER)
            _initialised = True


def holding_back(fn, marker: str) -> str | None:
    """Call ``fn()`` with the process's stderr (file descriptor 2, where native code prints) captured; lines that
    contain ``marker`` are returned (None if none), every other line is written back to stderr."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no file descriptor 2: nothing to hold back
        fn()
        return None
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            fn()
        finally:
            with contextlib.suppress(OSError, ValueError):
                sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            lines = tmp.read().decode(errors="replace").splitlines(keepends=True)
    rest = "".join(line for line in lines if marker not in line)
    if rest:
        sys.stderr.write(rest)
        sys.stderr.flush()
    held = "".join(line for line in lines if marker in line).strip()
    return held or None


_pool: ThreadPoolExecutor | None = None


def frame_chunks(t: torch.Tensor, T: int) -> list[slice]:
    """Ranges of T independent items (frames, queries) to launch side by side. Warp runs a CPU launch on one thread
    and lets go of the GIL while it runs, so on the CPU the items are split into one range per torch thread
    (``torch.get_num_threads()``, which OMP_NUM_THREADS sets); on CUDA a launch already fills the device: one range."""
    n = 1 if t.is_cuda else max(1, min(T, torch.get_num_threads()))
    edges = [round(i * T / n) for i in range(n + 1)]
    return [slice(edges[i], edges[i + 1]) for i in range(n)]


def map_chunks(fn, chunks: list) -> list:
    """``fn(chunk)`` for every chunk, on worker threads when there are several; the results in order."""
    global _pool
    if len(chunks) == 1:
        return [fn(chunks[0])]
    if _pool is None:
        with _init_lock:
            if _pool is None:
                _pool = ThreadPoolExecutor(max_workers=max(2, os.cpu_count() or 2), thread_name_prefix="warp-cpu")
    return list(_pool.map(fn, chunks))


def wp_device(t: torch.Tensor) -> wp.context.Device:
    """The Warp device that matches a torch tensor's device (``cpu`` or ``cuda:N``)."""
    init()
    return wp.device_from_torch(t.device)


def to_wp(t: torch.Tensor, dtype=None) -> wp.array:
    """A zero-copy Warp view of a contiguous, detached tensor (never allocates a gradient)."""
    init()
    t = t.detach()
    if not t.is_contiguous():
        t = t.contiguous()
    if dtype is None:
        return wp.from_torch(t, requires_grad=False)
    return wp.from_torch(t, dtype=dtype, requires_grad=False)


@contextlib.contextmanager
def stream_of(t: torch.Tensor):
    """Run Warp launches on the current torch stream of ``t``'s device (no-op on the CPU)."""
    init()
    if t.is_cuda:
        with wp.ScopedStream(wp.stream_from_torch(t.device)):
            yield
    else:
        yield


def same_device(name: str, *tensors: torch.Tensor) -> torch.device:
    """Check every tensor sits on one device and return it; raise ``ValueError`` naming ``name``."""
    devs = {t.device for t in tensors if t is not None}
    if len(devs) > 1:
        raise ValueError(f"{name}(): all inputs must be on one device, got {sorted(map(str, devs))}")
    return next(iter(devs))


def check_shape(name: str, arg: str, t: torch.Tensor, shape: tuple) -> None:
    """Raise ``ValueError`` unless ``t.shape`` matches ``shape`` (``None`` = any size)."""
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name}(): {arg} must be a torch.Tensor, got {type(t).__name__}")
    ok = t.dim() == len(shape) and all(s is None or s == d for s, d in zip(shape, t.shape))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name}(): {arg} must have shape {want}, got {tuple(t.shape)}")


def check_float(name: str, arg: str, t: torch.Tensor) -> None:
    """Raise ``TypeError`` unless ``t`` is float32 (the kernels' dtype)."""
    if t.dtype != torch.float32:
        raise TypeError(f"{name}(): {arg} must be float32, got {t.dtype}")


def _version(t: torch.Tensor) -> int | None:
    try:
        return t._version  # in-place changes bump it; a view shares its base's
    except RuntimeError:  # an inference-mode tensor keeps no version: nothing is cached for it
        return None


def set_index_bounds(t: torch.Tensor, lo: int, hi: int) -> None:
    """Record that every value of the integer tensor ``t`` lies in [lo, hi], until it is changed in place (an op's
    output whose range the op knows: a z-buffer's face ids, the frame column of a ``nonzero``)."""
    v = _version(t)
    if v is not None:
        t._s3o_bounds = (v, int(lo), int(hi))


def _recorded(t: torch.Tensor | None) -> tuple[int, int] | None:
    b = getattr(t, "_s3o_bounds", None) if t is not None else None
    return (b[1], b[2]) if b is not None and b[0] == _version(t) else None


def index_bounds(t: torch.Tensor, within: tuple[int, int]) -> tuple[int, int]:
    """Bounds ``(lo, hi)`` of a non-empty integer tensor's values, for an op's check that they lie in ``within``.

    On a GPU reading a value is a host sync, so a tensor's bounds are read once and kept until it changes in place:
    a fixed index buffer (a mesh's faces between resamplings) is read on its first check only. A tensor with
    recorded bounds (:func:`set_index_bounds`) costs no read, nor does a view of one (a slice of a z-buffer) when its
    base's bounds lie in ``within`` (they bound the view's values, perhaps loosely: otherwise the view is read).
    """
    b = _recorded(t)
    if b is None:
        base = _recorded(t._base)
        if base is not None and within[0] <= base[0] and base[1] <= within[1]:
            return base
        b = tuple(int(v) for v in torch.stack(torch.aminmax(t)).tolist())
        set_index_bounds(t, *b)
    return b


def cached(t: torch.Tensor, key: str, fn):
    """``fn()``, computed once per tensor ``t`` and in-place change and kept on it under ``key``: what an op derives
    from a fixed input (a mesh's neighbour lists from its faces) is derived on the first call only (on a GPU,
    without the host syncs of its dynamic shapes)."""
    v = _version(t)
    memo = getattr(t, "_s3o_memo", None)
    if v is not None and memo is not None and key in memo and memo[key][0] == v:
        return memo[key][1]
    out = fn()
    if v is not None:
        if memo is None:
            memo = t._s3o_memo = {}
        memo[key] = (v, out)
    return out
