"""``gcm_pipeline.interrupts``: a block run under ``deferred()`` finishes before Ctrl-C lands."""

from __future__ import annotations

import os
import signal
import time

import pytest


def test_an_interrupt_taken_by_another_thread_waits_for_the_swap_to_finish():
    """While a run directory is swapped in, Ctrl-C waits, in a process with threads too.

    A signal mask holds a signal in the main thread only: another thread (BLAS,
    tqdm, a pool's feeder) takes it and Python raises it in the main thread in
    the middle of the swap, which left the results missing or a hidden leftover.
    """
    import threading

    from gcm_pipeline import interrupts

    stop = threading.Event()
    other = threading.Thread(target=stop.wait, daemon=True)  # a thread that may take it
    other.start()
    previous = interrupts.install()
    steps = []
    try:
        with pytest.raises(KeyboardInterrupt):
            with interrupts.deferred():
                os.kill(os.getpid(), signal.SIGINT)
                for i in range(3):
                    time.sleep(0.05)  # the handler would run here
                    steps.append(i)
        assert steps == [0, 1, 2]  # the whole block ran, then the interrupt came
    finally:
        interrupts.restore(previous)
        interrupts.clear()
        stop.set()
