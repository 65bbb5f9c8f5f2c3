"""Progress on stderr: a tqdm bar on a terminal; elsewhere nothing, or a line now and then.

* :func:`bar`: a tqdm bar that shows only when asked for and stderr is a
  terminal (a log file or CI gets nothing): the pipeline's stages, a study's
  placements. With ``lines=True`` (a study's placements), off a terminal it
  is a :class:`LineBar` instead: a plain line every few seconds.
* :class:`Reporter`: per-item progress of a long step (the reachability
  stage's poses): the same bar on a terminal; otherwise a line on stderr every
  :data:`PROGRESS_INTERVAL_S` seconds, and one at the end when any was written.
* :func:`note`: one status line (``study: starting Ray (2 workers)...``).

Off a terminal the lines come every :data:`PROGRESS_INTERVAL_S` seconds, or
every ``GCM_PROGRESS_INTERVAL_S`` seconds when that environment variable holds
a positive number (a CI log that wants fewer lines, a test that wants them sooner).
"""

from __future__ import annotations

import math
import os
import sys
import threading
import time
from typing import Any

from tqdm.auto import tqdm

__all__ = ["PROGRESS_INTERVAL_S", "LineBar", "Reporter", "bar", "interval", "note"]

#: Seconds between progress lines when stderr is not a terminal.
PROGRESS_INTERVAL_S = 5.0

#: Environment variable that sets the seconds between progress lines off a terminal.
INTERVAL_ENV = "GCM_PROGRESS_INTERVAL_S"


#: When this process last printed a progress line (``time.perf_counter``).
_last_line = [0.0]


def _say(text: str) -> None:
    """Print a progress line on stderr and note when."""
    _last_line[0] = time.perf_counter()
    print(text, file=sys.stderr, flush=True)


def interval() -> float:
    """Seconds between progress lines off a terminal (``GCM_PROGRESS_INTERVAL_S`` or the default).

    A value that is not a positive finite number is ignored.
    """
    try:
        value = float(os.environ.get(INTERVAL_ENV, ""))
    except ValueError:
        return PROGRESS_INTERVAL_S
    return value if math.isfinite(value) and value > 0 else PROGRESS_INTERVAL_S


def note(text: str, *, enabled: bool = True) -> None:
    """Print one status line on stderr (on a terminal and off it), unless not ``enabled``."""
    if enabled:
        print(text, file=sys.stderr, flush=True)


def bar(
    total: int,
    desc: str,
    unit: str,
    *,
    enabled: bool = True,
    lines: bool = False,
    stages: bool = False,
    **options: Any,
) -> Any:
    """A tqdm bar on stderr, shown when ``enabled`` and stderr is a terminal.

    Otherwise the bar is disabled: its methods (``update``,
    ``set_postfix_str``, ``close``, ...) do nothing; with ``lines``, off a
    terminal, a :class:`LineBar` prints a line every few seconds instead.

    Args:
        total: Number of items.
        desc: The bar's label.
        unit: What an item is (``"stage"``, ``"placement"``).
        enabled: False: never shown.
        lines: Off a terminal, print progress lines (:class:`LineBar`).
        stages: The lines name the running stage (its postfix) instead of a rate.
        **options: Further tqdm options (``leave``, ``initial``, ``unit_scale``, ...).
    """
    if enabled and lines and not sys.stderr.isatty():
        initial = int(options.get("initial", 0))
        return LineBar(total, desc, unit, initial=initial, stages=stages)
    return tqdm(total=total, desc=desc, unit=unit, disable=not enabled or None, **options)


def _rate(rate: float) -> str:
    """``0.045``, ``3.1``, ``41`` or ``4,100``."""
    if rate >= 10:
        return f"{rate:,.0f}"
    return f"{rate:.1f}" if rate >= 0.1 else f"{rate:.2g}"


class LineBar:
    """A study's progress off a terminal: a line on stderr every :func:`interval` seconds.

    ``study: 12/48 placements, 3.1 placements/s, eta 12 s, best 0.806 (#7)``:
    the rate counts the items finished since this bar started (resumed ones
    are in ``initial``), the ETA the items left at that rate. The lines come
    from a background thread, so they keep coming while no item finishes
    (a slow placement, a worker starting). :meth:`close` stops it and prints a
    last line when any was printed. It has the subset of tqdm's interface a
    study uses: ``update``, ``total``, ``n``, ``set_postfix_str``, ``refresh``,
    ``close``.

    With ``stages`` the items are a run's stages, too unequal for a rate: the
    lines name a stage that has run for an interval (the postfix) and for how
    long, ``gcm: stage 9/9 (publish) for 5 s``; short stages print nothing,
    and none comes within an interval of another progress line (the
    reachability stage prints its own).

    Args:
        total: Number of items.
        desc: Label of the lines.
        unit: What an item is (the lines say ``units``).
        initial: Items already done when it starts.
        stages: The items are stages (see above).
    """

    def __init__(
        self, total: int, desc: str, unit: str, *, initial: int = 0, stages: bool = False
    ) -> None:
        self.stages = stages
        self.total = int(total)
        self.n = self.initial = int(initial)
        self.desc, self.unit = desc, unit
        self.postfix = ""
        self.lines = 0
        self.start = self._stage_start = time.perf_counter()
        self._stop = threading.Event()
        self._every = max(interval(), 0.05)
        self._thread = threading.Thread(target=self._tick, name="gcm-progress", daemon=True)
        self._thread.start()

    def _tick(self) -> None:
        while not self._stop.wait(self._every):
            if not self.stages:
                self._print()
                continue
            now, enough = time.perf_counter(), 0.9 * self._every
            if now - self._stage_start >= enough and now - _last_line[0] >= enough:
                self._print()  # a long stage, and no other progress line meanwhile

    def _print(self) -> None:
        self.lines += 1
        _say(self.line())

    def line(self) -> str:
        """The current line."""
        elapsed = max(time.perf_counter() - self.start, 1e-9)
        done = self.n - self.initial
        units = f"{self.unit}s"
        if self.stages:
            if self.n >= self.total:
                return f"{self.desc}: {self.n}/{self.total} {units} in {elapsed:.1f} s"
            running = f" ({self.postfix})" if self.postfix else ""
            took = time.perf_counter() - self._stage_start
            return f"{self.desc}: {self.unit} {self.n + 1}/{self.total}{running} for {took:.0f} s"
        text = f"{self.desc}: {self.n:,}/{self.total:,} {units}"
        if done <= 0:
            text += f", none finished yet ({elapsed:.0f} s)"
        elif self.n >= self.total:
            text += f", {_rate(done / elapsed)} {units}/s, in {elapsed:.1f} s"
        else:
            rate = done / elapsed
            text += f", {_rate(rate)} {units}/s, eta {(self.total - self.n) / rate:.0f} s"
        return text + (f", {self.postfix}" if self.postfix else "")

    def update(self, count: int = 1) -> None:
        """``count`` more items are finished."""
        self.n += count

    def set_postfix_str(self, text: str) -> None:
        """Text appended to the lines (``best 0.806 (#7)``); with ``stages``, the stage begun."""
        self.postfix = text
        self._stage_start = time.perf_counter()

    def refresh(self) -> None:
        """Nothing to redraw (a tqdm method)."""

    def close(self) -> None:
        """Stop the lines; print the last one when any was printed."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join()
        if self.lines:
            self._print()


class Reporter:
    """Per-item progress: a bar on a terminal, else a log line every few seconds.

    On a terminal: a tqdm bar with rate and ETA. Otherwise (a log file, CI):
    a line on stderr every :data:`PROGRESS_INTERVAL_S` seconds, and one at the
    end when any was written (a short run writes none). Called with the number
    of items just finished.

    Args:
        total: Number of items.
        enabled: False: report nothing.
        desc: Label of the bar and the lines.
        unit: What an item is (the lines say ``units``).
    """

    def __init__(
        self, total: int, enabled: bool = True, desc: str = "progress", unit: str = "item"
    ) -> None:
        self.total = int(total)
        self.done = 0
        self.desc = desc
        self.unit = unit
        self.start = time.perf_counter()
        self.last = self.start
        self.bar: Any = None
        self.lines = 0
        self.every = interval()
        self.enabled = enabled and total > 0
        if self.enabled and sys.stderr.isatty():
            self.bar = bar(self.total, desc, unit, unit_scale=True, leave=False)

    def __call__(self, count: int) -> None:
        """``count`` more items are finished."""
        if not self.enabled:
            return
        self.done += count
        if self.bar is not None:
            self.bar.update(count)
            return
        now = time.perf_counter()
        if now - self.last >= self.every and self.done < self.total:
            self.last = now
            self.lines += 1
            _say(self.line(now))

    def line(self, now: float | None = None) -> str:
        """``reachability: 12,000/56,294 poses (21 %), 4,100 poses/s, ETA 11 s``."""
        now = time.perf_counter() if now is None else now
        elapsed = max(now - self.start, 1e-9)
        rate = self.done / elapsed
        left = (self.total - self.done) / rate if rate > 0 else float("nan")
        pct = 100.0 * self.done / max(self.total, 1)
        eta = f", ETA {left:.0f} s" if self.done < self.total else f" in {elapsed:.1f} s"
        units = f"{self.unit}s"
        return (
            f"{self.desc}: {self.done:,}/{self.total:,} {units} ({pct:.0f} %), "
            f"{rate:,.0f} {units}/s{eta}"
        )

    def close(self) -> None:
        """Remove the bar (or write the last line)."""
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.close()
        elif self.lines:
            _say(self.line())

    def __enter__(self) -> Reporter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
