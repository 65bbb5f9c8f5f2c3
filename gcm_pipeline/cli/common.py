"""What every ``gcm`` command shares.

The one-line-error parser, the common options, the logger, the grasp table
printout and the live viewer.

Nothing heavy is imported here: each command imports what it needs when it runs.
"""

from __future__ import annotations

import argparse
import logging
import time
import typing
from typing import Any

from gcm_pipeline import interrupts

log = logging.getLogger("gcm_pipeline")

EXIT_USER_ERROR = 2


class Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line ``error: ...`` (exit status 2)."""

    def error(self, message: str) -> typing.NoReturn:
        """Print ``error: PROG: MESSAGE (see PROG --help)`` on stderr and exit with status 2."""
        line = " ".join(f"{self.prog}: {message}".split())
        self.exit(EXIT_USER_ERROR, f"error: {line} (see {self.prog} --help)\n")


def common_options(debug_help: bool = True) -> Parser:
    """The options of every command: ``-v``, ``--quiet``, ``--debug``."""
    p = Parser(add_help=False)
    p.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=0,
        help="more log output (-v: info, -vv: debug)",
    )
    p.add_argument(
        "--quiet",
        "-q",
        action="store_true",
        help="no progress bars, no log output but errors; gcm run prints only the run "
        "directory's path on stdout (for scripts; with --meshcat also the viewer URL)",
    )
    p.add_argument("--debug", action="store_true", help="show tracebacks of user errors")
    return p


#: Why points of a cloud were not kept, as ``gcm run`` and ``gcm show`` name them.
_CLOUD_DROPS = {
    "non_finite": "not finite (dropped)",
    "no_depth": "no depth",
    "beyond_max_depth": "beyond max_depth",
    "outside_crop": "outside the crop",
    "excluded_segments": "in excluded segments",
    "excluded_object": "near the object",
}


def cloud_line(name: str, voxel_size: float, counts: dict[str, Any]) -> str:
    """``name: K of N points kept -> V voxels of S cm (why the others were not)``."""
    why = ", ".join(
        f"{counts[k]:,} {what}"
        for k, what in _CLOUD_DROPS.items()
        if isinstance(counts.get(k), int) and counts[k]
    )
    return (
        f"{name}: {counts['kept']:,} of {counts['read']:,} points kept -> "
        f"{counts['voxels']:,} voxels of {100 * voxel_size:g} cm" + (f" ({why})" if why else "")
    )


def _fmt(v: Any, width: int = 9) -> str:
    if isinstance(v, float):
        return f"{v:{width}.4f}" if abs(v) < 1e4 else f"{v:{width}.3g}"
    return f"{v!s:>{width}}"


def format_top(top: list[dict[str, Any]], metric: str = "yoshikawa") -> str:
    """A small text table of the top grasps (rank, position, quaternion, metrics)."""
    from gcm_pipeline.ranking.metrics import METRIC_COLUMNS

    if not top:
        return "  (no reachable grasp)"
    cols = ["rank", "origin", "x", "y", "z", "qw", "qx", "qy", "qz", "manipulability"]
    column = METRIC_COLUMNS.get(metric, metric)
    if column not in cols and column in top[0]:
        cols.append(column)
    widths = {"rank": 4, "origin": 12, column: max(9, len(column))}
    head = "  ".join(f"{c:>{widths.get(c, 9)}}" for c in cols)
    lines = ["  " + head]
    for item in top:
        cells = [_fmt(item.get(c, ""), widths.get(c, 9)) for c in cols]
        lines.append("  " + "  ".join(cells))
    return "\n".join(lines)


def show_in_viewer(
    grasps: Any, manifold: Any, robot: Any, config: Any, *, wait: bool, clouds: Any = ()
) -> None:
    """Publish to the live viewer; wait for Ctrl-C, or leave its server running."""
    from gcm_pipeline.pipeline.outputs import open_viewer

    viewer = open_viewer(grasps, manifold, robot, config, detach=not wait, clouds=clouds)
    try:
        print(f"meshcat viewer: {viewer.url}", flush=True)
        if wait:
            print("press Ctrl-C to quit", flush=True)
            try:
                while True:
                    time.sleep(0.5)
            except KeyboardInterrupt:  # the way to close the viewer: not an interruption
                interrupts.clear()
                print()
        elif viewer.server_pid is not None:
            print(
                f"the viewer's server keeps running (pid {viewer.server_pid}); "
                f"stop it with: kill {viewer.server_pid}",
                flush=True,
            )
    finally:
        viewer.close()
