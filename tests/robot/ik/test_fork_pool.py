"""The IK engine's process pool (``robot.ik.pool.ForkPool``) survives a worker's death."""

from __future__ import annotations

import os
import signal
import time


def test_worker_pool_terminates_after_a_worker_died_waiting_for_work():
    """An idle worker waits for a task holding the task queue's lock; killed then (a
    SIGTERM to the process group), it never releases it. The engine's pool still
    terminates (the standard one waits for that lock for ever)."""
    import threading

    from gcm_pipeline.robot.ik.pool import ForkPool

    pool = ForkPool(1)
    assert pool.apply(abs, (-3,)) == 3  # the worker is up, now idle in get()
    worker = pool._pool[0]
    time.sleep(0.2)
    os.kill(worker.pid, signal.SIGKILL)
    worker.join(timeout=10)
    done = threading.Event()

    def stop() -> None:
        pool.terminate()
        pool.join()
        done.set()

    threading.Thread(target=stop, daemon=True).start()
    assert done.wait(timeout=30), "terminate() hung on the dead worker's lock"
