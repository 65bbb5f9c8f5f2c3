"""``python -m gcm_pipeline`` and the ``gcm`` command.

The signal handlers come first, before the command line (and NumPy,
Pinocchio, ...) load, so that a Ctrl-C, SIGTERM or SIGHUP at any moment ends
``gcm`` with its one line (``interrupted``) and status (130, 128 + signal);
once the command has returned they are ignored while the process exits.

The exit skips the interpreter's last garbage collection over what the command
loaded (:func:`gc.freeze` at exit): after a run on a big point cloud that pass
alone took seconds, also after an interrupt. Exit handlers still run, and
objects are still freed by their reference counts.
"""

from __future__ import annotations

import atexit
import gc
import sys

from gcm_pipeline import interrupts


def entry() -> int:
    """Run the ``gcm`` command line (``sys.argv``); returns the exit status."""
    try:
        interrupts.install()
        # imported here, after the handlers: a Ctrl-C while the command line loads is handled
        from gcm_pipeline.cli import main

        return main()
    except KeyboardInterrupt as exc:  # before main() handles them (while it loads)
        return interrupts.report(exc)
    finally:
        interrupts.ignore()
        interrupts.clear()
        atexit.unregister(gc.freeze)  # once, however many commands ran in this process
        atexit.register(gc.freeze)  # run first of the exit handlers (last registered)


if __name__ == "__main__":
    sys.exit(entry())
