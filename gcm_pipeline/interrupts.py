"""The interrupts the ``gcm`` command received (Ctrl-C, SIGTERM, SIGHUP).

``gcm`` handles these signals by raising :class:`KeyboardInterrupt` (or
:class:`Terminated`) in the main thread, so that every clean-up runs. Python
drops an exception raised while it runs a finaliser or a weak-reference
callback ("Exception ignored in ..."): an interrupt landing there would be
lost and the command would go on, even replace a previous run. So the
handlers also *record* the signal, and the places that make a result final
call :func:`check`, which raises the interrupt again if one was recorded.
Outside ``gcm`` (the Python API) nothing is recorded and :func:`check` does
nothing.

This module imports nothing heavy: ``python -m gcm_pipeline`` installs the
handlers before anything else loads (:func:`install`).
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator
from typing import Any

__all__ = [
    "Terminated",
    "check",
    "clear",
    "deferred",
    "held",
    "ignore",
    "install",
    "interrupt_cause",
    "release",
    "report",
    "restore",
]

#: The signals ``gcm`` turns into an interrupt of the main thread.
NAMES = ("SIGINT", "SIGTERM", "SIGHUP")
_SIGNALS = tuple(getattr(signal, name) for name in NAMES if hasattr(signal, name))


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised in the main thread so it unwinds like Ctrl-C.

    Attributes:
        signum: The signal number.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


_received: int | None = None


def clear() -> None:
    """Forget the recorded interrupt (at the start of a command)."""
    global _received
    _received = None


def _interrupt(signum: int) -> KeyboardInterrupt:
    return KeyboardInterrupt() if signum == signal.SIGINT else Terminated(signum)


def raise_interrupt(signum: int, frame: Any = None) -> None:
    """Signal handler: record the signal and raise its interrupt."""
    global _received
    _received = signum
    raise _interrupt(signum)


def check() -> None:
    """Raise the recorded interrupt again (it may have been lost); nothing if none."""
    if _received is not None:
        raise _interrupt(_received)


def _set(handler: Any) -> dict[int, Any]:
    """Set ``handler`` for the signals of :data:`NAMES`; returns the previous handlers.

    Outside the main thread (where Python allows no handler) nothing is set.
    """
    if threading.current_thread() is not threading.main_thread():
        return {}
    sigs = [getattr(signal, n) for n in NAMES if hasattr(signal, n)]
    return {sig: signal.signal(sig, handler) for sig in sigs}


def install() -> dict[int, Any]:
    """Handle the signals with :func:`raise_interrupt`; returns the previous handlers."""
    return _set(raise_interrupt)


def restore(previous: dict[int, Any]) -> None:
    """Put back the handlers :func:`install` returned."""
    for sig, handler in previous.items():
        signal.signal(sig, handler)


@contextlib.contextmanager
def held(grace: float | None = None) -> Iterator[list[int]]:
    """Record the interrupts instead of acting on them while the block runs.

    For code that must not be cut in the middle (starting Ray: an interrupt
    inside its start-up left its agents running or crashed the interpreter at
    exit). Only signals handled by a Python function are held (a default
    action stays what it is); the previous handlers are back after the block.
    The caller passes the yielded list to :func:`release` once it can clean up.

    Args:
        grace: Seconds a held interrupt may wait; then it is raised inside the
            block after all (joining a Ray cluster that never answers must not
            make SIGTERM wait forever). None: it waits for the block's end.
    """
    got: list[int] = []
    late = threading.Event()
    timers: list[threading.Timer] = []

    def record(signum: int, frame: Any) -> None:
        if late.is_set():
            raise_interrupt(signum)
        got.append(signum)
        if grace is not None and not timers:
            timer = threading.Timer(grace, _deliver_late, (late, got[0]))
            timer.daemon = True
            timers.append(timer)
            timer.start()

    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for name in NAMES:
            sig = getattr(signal, name, None)
            if sig is not None and callable(signal.getsignal(sig)):
                previous[sig] = signal.signal(sig, record)
    try:
        yield got
    finally:
        for timer in timers:
            timer.cancel()
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Hold Ctrl-C, SIGTERM and SIGHUP until the block is done (they arrive afterwards).

    Used around the few renames that swap a run directory in, and around the
    clean-up after a failure, so that an interrupt cannot leave them half done.
    A signal mask alone does not do it: it holds the signal in the main thread
    only, the process's other threads (BLAS, tqdm, a pool's feeder) take it,
    and Python then runs its handler in the main thread inside the block. So
    the handlers *record* the signals while the block runs (:func:`held`),
    and the first one is raised again once it is done.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    block = getattr(signal, "pthread_sigmask", None)
    with held() as got:
        previous = block(signal.SIG_BLOCK, _SIGNALS) if block is not None else None
        try:
            yield
        finally:
            if previous is not None:
                block(signal.SIG_SETMASK, previous)  # a pending signal is recorded now
    if got:
        signal.raise_signal(got[0])  # the handlers are back: delivered as usual


def _deliver_late(late: threading.Event, signum: int) -> None:
    """Deliver a held interrupt again, now to be raised (see :func:`held`)."""
    late.set()
    signal.raise_signal(signum)


def release(got: list[int]) -> None:
    """Raise the first interrupt :func:`held` recorded (nothing if none)."""
    global _received
    if got:
        _received = got[0]
        raise _interrupt(got[0])


def ignore() -> None:
    """Ignore the signals from now on (the command is done; the process exits)."""
    _set(signal.SIG_IGN)


def report(exc: KeyboardInterrupt) -> int:
    """Print the one line of an interrupt; return its exit status (130 or 128 + signal)."""
    signum = exc.signum if isinstance(exc, Terminated) else _received
    if signum is not None and signum != signal.SIGINT:
        print(f"interrupted ({signal.Signals(signum).name})", file=sys.stderr)
        return 128 + signum
    print("interrupted", file=sys.stderr)
    return 130


def interrupt_cause(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C (or :class:`Terminated`) behind an exception, if any.

    A library may turn an interrupt that arrives inside its own code into an
    error of its own (pydantic does while it serialises a config: a
    ``PydanticSerializationError`` caused by the ``KeyboardInterrupt``); such
    an error is an interrupt all the same.
    """
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, KeyboardInterrupt):
            return cur
        seen.add(id(cur))
        cur = cur.__cause__ or cur.__context__
    return None
