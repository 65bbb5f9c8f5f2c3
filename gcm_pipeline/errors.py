"""Project exceptions.

Every error a user can cause (a bad config key, an unreadable file, a
non-rigid matrix, an unknown robot) is a :class:`GcmError`. The CLI prints
such an error as one line ``error: <message>`` and exits with status 2;
any other exception is a bug and keeps its traceback.

Messages name the key, file, row or value at fault and, where there is a
closed set of valid values, list them (see :func:`unknown_choice`). The same
evidence rides on the exception as attributes (``key``, ``value``,
``choices``, ``path``, ``row``; None where not known), so a caller or a test
reads it without parsing the message (see :func:`choice_error`).
"""

from __future__ import annotations

import difflib
import reprlib
from collections.abc import Iterable
from pathlib import Path
from typing import Any, TypeVar

__all__ = [
    "ConfigError",
    "FrameNotFoundError",
    "GcmError",
    "GeometryError",
    "InputError",
    "OutputError",
    "PublishError",
    "RobotSpecError",
    "WorkerLostError",
    "choice_error",
    "clip",
    "unknown_choice",
]

#: Longest quote of a user's value in a message [characters].
MAX_QUOTE = 200


class GcmError(Exception):
    """Root of every error a user of gcm_pipeline can cause.

    ``str(exc)`` is the one-line message; the keyword arguments are the
    evidence it names, kept as attributes (None where not known).

    Attributes:
        key: Dotted config key or column at fault (``ik.backend``, ``qw``).
        value: The value at fault, as given.
        choices: The valid values of a closed set, sorted.
        path: The file at fault.
        row: The line of that file (1-based, as the message names it), or the
            row of an array.
    """

    #: The command line's exit status for it.
    exit_status = 2

    def __init__(
        self,
        *args: object,
        key: str | None = None,
        value: Any = None,
        choices: Iterable[str] | None = None,
        path: str | Path | None = None,
        row: int | None = None,
    ) -> None:
        super().__init__(*args)
        self.key = key
        self.value = value
        self.choices = None if choices is None else tuple(choices)
        self.path = path
        self.row = row


class ConfigError(GcmError):
    """A config file or value is invalid (names the key at fault)."""


class InputError(GcmError):
    """Input data (grasp poses, files, arrays) is invalid."""


class GeometryError(InputError):
    """Geometric input violates a precondition (non-rigid, non-finite, degenerate)."""


class RobotSpecError(GcmError):
    """A robot spec cannot be found or is invalid."""


class FrameNotFoundError(RobotSpecError):
    """A frame named in a robot spec does not exist in the model."""


class OutputError(GcmError):
    """The run directory cannot be written (exists, is a file, not writable)."""


class PublishError(GcmError):
    """Publishing results failed (meshcat server unreachable, browser missing)."""


class WorkerLostError(GcmError):
    """A worker process died before returning its result (killed, e.g. out of memory).

    Not the input's fault: the command line exits with status 1, not 2.
    """

    exit_status = 1


def clip(value: object, limit: int = MAX_QUOTE) -> str:
    """The :func:`repr` of a user's value for a message, at most about ``limit`` characters.

    Built with :mod:`reprlib`, so a huge string or container is never repr'd
    whole (a 39 MB value stays a short quote, and its repr costs nothing):
    long strings keep their start and end, containers their first items.

    Args:
        value: Any value read from a config or a file.
        limit: Characters to keep.

    Returns:
        A one-line string.
    """
    short = reprlib.Repr()
    short.maxlevel = 4
    short.maxstring = limit
    short.maxother = limit
    short.maxlist = short.maxtuple = short.maxdict = short.maxset = 12
    try:
        text = " ".join(short.repr(value).split())
    except Exception:  # a broken __repr__ must not hide the real error
        text = f"<{type(value).__name__}>"
    if len(text) > limit:
        text = text[: limit - 3] + "..."
    if isinstance(value, str) and len(value) > limit:
        text += f" ({len(value):,} characters)"
    return text


E = TypeVar("E", bound=GcmError)


def unknown_choice(kind: str, value: object, choices: Iterable[str]) -> str:
    """Build the message for a value outside a closed set of names.

    Args:
        kind: What the value names, e.g. ``"projection"``.
        value: The value given by the user.
        choices: The valid names.

    Returns:
        A one-line message naming the value, the closest valid name if any
        is close, and all valid names.
    """
    names = sorted(str(c) for c in choices)
    text = value if isinstance(value, str) and len(value) <= MAX_QUOTE else clip(value)
    close = difflib.get_close_matches(str(text), names, n=1, cutoff=0.6)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"unknown {kind} {clip(value)}{hint}; valid: {', '.join(names)}"


def choice_error(
    cls: type[E],
    kind: str,
    value: object,
    choices: Iterable[str],
    *,
    key: str | None = None,
    prefix: str = "",
) -> E:
    """The error of a value outside a closed set: :func:`unknown_choice`'s message and evidence.

    Args:
        cls: The :class:`GcmError` subclass to build.
        kind: What the value names, e.g. ``"projection"``.
        value: The value given by the user.
        choices: The valid names.
        key: The config key or column that holds the value, where known.
        prefix: Text put before the message (``"robot 'ur5': home: "``).

    Returns:
        ``cls(prefix + unknown_choice(kind, value, choices))`` with ``key``,
        ``value`` and ``choices`` (sorted names) set; the caller raises it.
    """
    names = sorted(str(c) for c in choices)
    return cls(prefix + unknown_choice(kind, value, names), key=key, value=value, choices=names)
