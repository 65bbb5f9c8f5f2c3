"""The IK engine's process pool (``robot.ik.pool.ForkPool``) survives a worker's death."""

from __future__ import annotations

import os
import signal
import time


def _terminates(pool, timeout: float = 30.0) -> bool:
    """Whether ``pool.terminate(); pool.join()`` returns within ``timeout`` seconds."""
    import threading

    done = threading.Event()

    def stop() -> None:
        pool.terminate()
        pool.join()
        done.set()

    threading.Thread(target=stop, daemon=True).start()
    return done.wait(timeout=timeout)


def test_worker_pool_terminates_after_a_worker_died_waiting_for_work():
    """An idle worker waits for a task holding the task queue's lock; killed then (a
    SIGTERM to the process group), it never releases it. The engine's pool still
    terminates (the standard one waits for that lock for ever)."""

    from gcm_pipeline.robot.ik.pool import ForkPool

    pool = ForkPool(1)
    assert pool.apply(abs, (-3,)) == 3  # the worker is up, now idle in get()
    worker = pool._pool[0]
    time.sleep(0.2)
    os.kill(worker.pid, signal.SIGKILL)
    worker.join(timeout=10)
    assert _terminates(pool), "terminate() hung on the dead worker's lock"


def _die_while_sending(_: int) -> None:
    """In a worker: start sending a result (take the result queue's write lock, write
    a message header) and die there, as a worker killed mid-send does."""
    import struct
    import sys

    outqueue = sys._getframe(1).f_locals["outqueue"]  # the pool's worker loop
    outqueue._wlock.acquire()
    outqueue._writer._send(struct.pack("!i", 1 << 20))  # a message header, no body
    os.kill(os.getpid(), signal.SIGKILL)


def test_worker_pool_terminates_after_a_worker_died_sending_its_result():
    """A worker killed while it sends its result (the out-of-memory killer, a SIGKILL)
    holds the result queue's write lock and leaves half a message: the run reports the
    lost worker, and the pool still terminates (the standard one waits for ever)."""

    import pytest

    from gcm_pipeline.errors import WorkerLostError
    from gcm_pipeline.robot.ik.pool import ForkPool

    pool = ForkPool(2)
    with pytest.raises(WorkerLostError, match="killed by SIGKILL"):
        list(pool.ordered(_die_while_sending, [0]))
    workers = list(pool._pool)
    assert _terminates(pool), "terminate() hung on the dead worker's half-sent result"
    assert all(p.exitcode is not None for p in workers)  # no worker left behind
