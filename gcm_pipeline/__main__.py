"""``python -m gcm_pipeline`` and the ``gcm`` command.

The signal handlers come first, before the command line (and NumPy,
Pinocchio, ...) load, so that a Ctrl-C, SIGTERM or SIGHUP at any moment ends
``gcm`` with its one line (``interrupted``) and status (130, 128 + signal);
once the command has returned they are ignored while the process exits.
"""

from __future__ import annotations

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


if __name__ == "__main__":
    sys.exit(entry())
