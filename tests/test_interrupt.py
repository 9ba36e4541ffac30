"""Stop requests (s3o_warp/interrupt.py): SIGINT and SIGTERM set a flag that long loops check."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from s3o_warp import interrupt


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_inside_the_block_asks_for_a_stop_and_the_handlers_come_back(sig, sigint_raises):
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with interrupt.on_signals():
        interrupt.check("nothing")  # no request yet
        with interrupt.on_signals():  # nested (the CLI around the fit): one flag
            os.kill(os.getpid(), sig)  # handled here, in the main thread, before the next line
            assert interrupt.requested()
        assert interrupt.requested()
        with pytest.raises(interrupt.Interrupted, match="stopped during the loop"):
            interrupt.check("the loop")
    assert {s: signal.getsignal(s) for s in before} == before
    with interrupt.on_signals():  # the next outermost block starts afresh
        assert not interrupt.requested()


def test_a_sigint_found_ignored_stays_ignored_and_sigterm_still_stops():
    """``nohup s3o-fit ... &`` starts the fit with SIGINT ignored: inside the block it stays so (Ctrl-C of the
    terminal does not reach the job), SIGTERM still asks for a stop, and SIG_IGN is back after."""
    found = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with interrupt.on_signals():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGINT)
            assert not interrupt.requested()
            os.kill(os.getpid(), signal.SIGTERM)
            assert interrupt.requested()
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, found)


def test_a_stop_does_not_outlive_the_block_that_it_stopped():
    """The flag is cleared when the outermost block ends: loops run after a stopped fit (outside any block, or in
    another thread) are not stopped by it."""
    with pytest.raises(interrupt.Interrupted):
        with interrupt.on_signals():
            with interrupt.on_signals():
                interrupt.request()
            assert interrupt.requested()  # the outer block still sees the stop
            interrupt.check("the fit")
    assert not interrupt.requested()
    interrupt.check("the next loop")  # does not raise
    seen = []
    worker = threading.Thread(target=lambda: seen.append(_stop_in_a_block()))
    worker.start()
    worker.join()
    assert seen == [True] and not interrupt.requested()  # a block of another thread too


def _stop_in_a_block() -> bool:
    with interrupt.on_signals():
        interrupt.request()
        return interrupt.requested()


def test_the_signal_tests_pass_when_the_suite_is_started_with_sigint_ignored():
    """``nohup pytest ... &``: pytest starts with SIGINT ignored (a child inherits it); the tests that send SIGINT
    install Python's handler for themselves (``sigint_raises``) and put SIG_IGN back."""
    code = ("import signal, sys, pytest; signal.signal(signal.SIGINT, signal.SIG_IGN); "
            "rc = pytest.main(['-q', '-p', 'no:cacheprovider', sys.argv[1], '-k', 'not started_with_sigint_ignored']); "
            "assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN, 'a test left SIGINT changed'; sys.exit(rc)")
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-c", code, __file__], cwd=root, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
