"""Stop requests: Ctrl-C and SIGTERM set one flag that every long loop of a fit checks.

Inside :func:`on_signals` (the fit, the ``s3o-fit`` command) SIGINT and SIGTERM do not raise where the
interpreter happens to be: they ask for a stop, and each long loop (optical flow, the coarse, hypothesis,
warm-up and joint steps, resampling, export, renders) checks :func:`requested` once per item and leaves
through :class:`Interrupted` at a point from which the work can continue: the fit writes a checkpoint there
first, so ``--resume`` ends where an uninterrupted run ends. Every item is shorter than two seconds, so the
stop is that prompt.

A signal the process was started ignoring stays ignored (``nohup s3o-fit ... &``: the shell ignores SIGINT in a
background job, and the job keeps ignoring Ctrl-C of its terminal; SIGTERM still stops it). A stop lasts no longer
than the outermost block: the flag is cleared when it begins and when it ends.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading

log = logging.getLogger(__name__)

_flag = threading.Event()
_depth = 0  # open on_signals blocks, in every thread
_lock = threading.Lock()


class Interrupted(Exception):
    """A stop was requested (Ctrl-C, SIGTERM); the message says where the work stopped and what was kept."""


def request() -> None:
    """Ask every long loop to stop at its next check (safe from a signal handler and from any thread)."""
    _flag.set()


def requested() -> bool:
    """Has a stop been asked for since the outermost :func:`on_signals` began (or, outside one, since the last
    ended)?"""
    return _flag.is_set()


def check(where: str) -> None:
    """Raise :class:`Interrupted` naming ``where`` when a stop was requested."""
    if _flag.is_set():
        raise Interrupted(f"stopped during {where}")


def _handle(signum, frame) -> None:
    if not _flag.is_set():
        log.warning("%s: stopping at the next safe point (a checkpoint where there is one to write)",
                    signal.Signals(signum).name)
    request()


@contextlib.contextmanager
def on_signals():
    """SIGINT and SIGTERM request a stop inside the block (handlers are set in the main thread only); one found
    ignored (``SIG_IGN``) stays ignored. The stop flag is cleared when the outermost block (of any thread) begins and
    when it ends, so a stop never outlives the work it stopped; the previous handlers come back when the block
    ends."""
    global _depth
    main = threading.current_thread() is threading.main_thread()
    old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)} if main else {}
    with _lock:
        if _depth == 0:
            _flag.clear()
        _depth += 1
    try:
        for sig, h in old.items():
            if h is not signal.SIG_IGN:
                signal.signal(sig, _handle)
        yield
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)
        with _lock:
            _depth -= 1
            if _depth == 0:
                _flag.clear()
