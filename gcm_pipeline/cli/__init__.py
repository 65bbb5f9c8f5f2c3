"""Command line: ``gcm run | validate | schema | show | plot | query | export | view | ...``.

``gcm run CONFIG`` runs the whole pipeline and writes the run directory;
``gcm validate CONFIG`` only checks a config; ``gcm schema`` prints the
config's JSON Schema (``gcm validate STUDY`` checks a study file); ``gcm show
RUN_DIR`` prints the top-ranked grasps of a run (or a study directory's
summary); ``gcm plot RUN_DIR`` writes its plots; ``gcm query RUN_DIR --pose ...``
prints the nearest reachable grasp of a run's manifold to a pose; ``gcm export
RUN_DIR --format moveit | mcap | parquet | npz`` exports its grasps; ``gcm view RUN_DIR``
opens a saved run in the live meshcat viewer (nothing is recomputed);
``gcm study STUDY --out DIR`` runs a placement study on Ray and writes the
study directory; ``gcm robot SPEC`` prints what a robot spec configures (joints,
limits, frames, tool, collision pairs) and ``--out FILE`` writes its scene.

User errors (:class:`~gcm_pipeline.errors.GcmError`) print one line
``error: <message>`` on stderr and exit with status 2 (the traceback only
with ``--debug``); anything else is a bug and keeps its traceback.

The commands live in :mod:`~gcm_pipeline.cli.run` (run, validate, schema),
:mod:`~gcm_pipeline.cli.results` (show, plot, query, export, view; on a study
directory :mod:`~gcm_pipeline.cli.study_dir`), :mod:`~gcm_pipeline.cli.study`
(study, and validate of a study file) and :mod:`~gcm_pipeline.cli.robot`; each adds
its subparsers and imports its heavy libraries only when it runs, so that
``gcm --help`` starts without NumPy, SciPy or Pinocchio.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import signal
import sys
import traceback
from collections.abc import Iterator, Sequence
from typing import Any

from gcm_pipeline import __version__, interrupts
from gcm_pipeline.cli import results, robot, run, study
from gcm_pipeline.cli.common import Parser, common_options, log
from gcm_pipeline.errors import GcmError

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    """The ``gcm`` argument parser."""
    parser = Parser(
        prog="gcm",
        description="Grasp configuration manifolds: densify grasp candidates on dual "
        "quaternions, check which ones a robot reaches, rank them by manipulability.",
    )
    parser.add_argument("--version", action="version", version=f"gcm {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    common = common_options()
    for commands in (run, results, study, robot):
        commands.add_parsers(sub, common)
    return parser


def _setup_logging(verbose: int, quiet: bool) -> None:
    level = (
        logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
    )
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    for h in list(log.handlers):
        if getattr(h, "_gcm_cli", False):
            log.removeHandler(h)
    handler._gcm_cli = True  # type: ignore[attr-defined]
    log.addHandler(handler)
    log.setLevel(level)
    log.propagate = False
    logging.captureWarnings(True)


_COMMANDS = {**run.COMMANDS, **results.COMMANDS, **study.COMMANDS, **robot.COMMANDS}


@contextlib.contextmanager
def interrupt_on_termination() -> Iterator[None]:
    """Handle Ctrl-C, SIGTERM and SIGHUP with :func:`gcm_pipeline.interrupts.raise_interrupt`.

    Each raises :class:`~gcm_pipeline.interrupts.Terminated` (a :class:`KeyboardInterrupt`; plain
    ``KeyboardInterrupt`` for Ctrl-C) in the main thread, so every ``finally``
    and ``except BaseException`` runs: a run directory being written is
    removed. The signal is also recorded, so that an interrupt Python drops
    (raised inside a finaliser; it says nothing about it then) is raised again
    where a result becomes final (:func:`gcm_pipeline.interrupts.check`). The
    previous handlers come back afterwards. Outside the main thread the
    signals are not handled.
    """
    previous = interrupts.install()
    hook = sys.unraisablehook
    sys.unraisablehook = _quiet_dropped_interrupts(hook)
    try:
        yield
    finally:
        sys.unraisablehook = hook
        interrupts.restore(previous)


def _quiet_dropped_interrupts(hook: Any) -> Any:
    """An unraisable hook that is silent about a dropped interrupt (it is recorded)."""

    def quiet(unraisable: Any) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            return
        hook(unraisable)

    return quiet


#: Longest error line the CLI prints [characters].
MAX_ERROR_LINE = 2000


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``gcm`` command line; returns the exit status.

    Args:
        argv: Arguments without the program name (default: ``sys.argv[1:]``).

    Returns:
        0 on success, 2 on a user error (or bad usage), 1 when a worker process
        died (e.g. killed for lack of memory), 130 on Ctrl-C, 128 +
        the signal number on SIGTERM (143) or SIGHUP (129), 141 when the
        reader of the output goes away (``gcm validate | head -1``).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.verbose, args.quiet)
    interrupts.clear()
    try:
        with interrupt_on_termination():
            status = _COMMANDS[args.command](args)
            sys.stdout.flush()  # a closed pipe shows here, inside the handlers
            interrupts.check()  # an interrupt Python dropped on the way is not ignored
            return status
    except GcmError as exc:
        if args.debug:
            traceback.print_exc()
        message = " ".join(str(exc).split())
        if len(message) > MAX_ERROR_LINE:
            message = message[: MAX_ERROR_LINE - 3] + "..."
        print(f"error: {message}", file=sys.stderr)
        return exc.exit_status
    except BrokenPipeError:
        # the reader left (e.g. `| head`): no traceback, and none at exit either
        with contextlib.suppress(OSError, ValueError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except BaseException as exc:
        # Ctrl-C, SIGTERM, SIGHUP, also when a library wrapped it in an error of its own
        interrupt = interrupts.interrupt_cause(exc)
        if interrupt is None:
            raise
        return interrupts.report(interrupt)
    finally:
        interrupts.clear()  # a handled interrupt does not outlive the command
