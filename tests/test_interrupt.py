"""Stop requests (s3o_warp/interrupt.py): SIGINT and SIGTERM set a flag that long loops check."""

from __future__ import annotations

import os
import signal

import pytest

from s3o_warp import interrupt


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_inside_the_block_asks_for_a_stop_and_the_handlers_come_back(sig):
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
