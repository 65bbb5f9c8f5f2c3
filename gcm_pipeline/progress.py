"""Progress on stderr: a tqdm bar on a terminal; elsewhere nothing, or a log line now and then.

* :func:`bar`: a tqdm bar that shows only when asked for and stderr is a
  terminal (a log file or CI gets nothing): the pipeline's stages, a study's
  placements.
* :class:`Reporter`: per-item progress of a long step (the reachability
  stage's poses): the same bar on a terminal; otherwise a line on stderr every
  :data:`PROGRESS_INTERVAL_S` seconds, and one at the end when any was written.
"""

from __future__ import annotations

import sys
import time
from typing import Any

from tqdm.auto import tqdm

__all__ = ["PROGRESS_INTERVAL_S", "Reporter", "bar"]

#: Seconds between progress lines when stderr is not a terminal.
PROGRESS_INTERVAL_S = 5.0


def bar(total: int, desc: str, unit: str, *, enabled: bool = True, **options: Any) -> Any:
    """A tqdm bar on stderr, shown when ``enabled`` and stderr is a terminal.

    Otherwise the bar is disabled: its methods (``update``,
    ``set_postfix_str``, ``close``, ...) do nothing.

    Args:
        total: Number of items.
        desc: The bar's label.
        unit: What an item is (``"stage"``, ``"placement"``).
        enabled: False: never shown.
        **options: Further tqdm options (``leave``, ``initial``, ``unit_scale``, ...).
    """
    return tqdm(total=total, desc=desc, unit=unit, disable=not enabled or None, **options)


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
        if now - self.last >= PROGRESS_INTERVAL_S and self.done < self.total:
            self.last = now
            self.lines += 1
            print(self.line(now), file=sys.stderr, flush=True)

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
            print(self.line(), file=sys.stderr, flush=True)

    def __enter__(self) -> Reporter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
