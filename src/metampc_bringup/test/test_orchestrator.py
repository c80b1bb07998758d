"""The orchestrator's stop that a Ctrl-C cannot cut halfway (interrupts_deferred); the seeds
themselves are run by test/test_experiment.py."""
import os
import signal
import time

import pytest

from metampc_bringup.orchestration.orchestrator import interrupts_deferred


def test_a_signal_inside_waits_for_the_block_then_interrupts():
    before = signal.getsignal(signal.SIGINT)
    finished = []
    with pytest.raises(KeyboardInterrupt, match='signal 2'):
        with interrupts_deferred():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)        # the handler has run by now: the block goes on
            finished.append(True)
    assert finished == [True]
    assert signal.getsignal(signal.SIGINT) is before


def test_a_signal_ignored_before_stays_ignored_and_none_raises_nothing():
    previous = signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        with interrupts_deferred():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
        with interrupts_deferred():
            pass
    finally:
        signal.signal(signal.SIGTERM, previous)
