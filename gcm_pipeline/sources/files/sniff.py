r"""What a grasp file looks like from its first bytes, for a file read in the wrong format.

A reader that gets another format's file fails deep inside a parser
(``'utf-8' codec can't decode byte 0x89`` for an HDF5 file read as GraspGen
YAML). :func:`check_format` looks at the file's start first and names what
the file is and the ``format:`` that reads it:

================ ====================================== ===============================
looks like       from                                   ``format:``
================ ====================================== ===============================
HDF5             ``\x89HDF\r\n\x1a\n``                  acronym
NumPy ``.npy``   ``\x93NUMPY``                          npy, graspnet
zip (``.npz``)   ``PK\x03\x04`` / ``PK\x05\x06``        npz, contact_graspnet, graspnet
Python pickle    ``\x80`` + protocol 2..5               none (save plain arrays)
JSON             text starting with ``{`` or ``[``      graspgen
CSV              a first line of comma-separated        csv
                 names with ``x``, ``y``, ``z``
YAML             ``---``, ``key:`` or ``-`` first       graspgen
================ ====================================== ===============================

Anything else (an empty file, other text, other binary data) is left to the
format's reader and its own message.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from gcm_pipeline.errors import InputError

__all__ = ["EXPECTED_KINDS", "Sniffed", "check_format", "sniff"]

#: Bytes looked at.
_HEAD = 1 << 16


@dataclass(frozen=True)
class Sniffed:
    """What a file looks like.

    Attributes:
        kind: ``hdf5``, ``npy``, ``zip``, ``pickle``, ``json``, ``csv`` or ``yaml``.
        description: For a message, e.g. ``"an HDF5 file"``.
        formats: The ``format:`` values that read such a file.
    """

    kind: str
    description: str
    formats: tuple[str, ...]


#: The kinds of file each ``format:`` reads.
EXPECTED_KINDS: dict[str, frozenset[str]] = {
    "acronym": frozenset({"hdf5"}),
    "npy": frozenset({"npy"}),
    "npz": frozenset({"zip"}),
    "csv": frozenset({"csv"}),
    "graspgen": frozenset({"json", "yaml"}),
    "contact_graspnet": frozenset({"zip"}),
    "graspnet": frozenset({"npy", "zip"}),
}

_WHAT = {
    "acronym": "an ACRONYM HDF5 file",
    "npy": "a NumPy .npy array",
    "npz": "a NumPy .npz archive",
    "csv": "a CSV table",
    "graspgen": "GraspGen JSON or YAML",
    "contact_graspnet": "a Contact-GraspNet .npz archive",
    "graspnet": "a GraspNet .npy array or .npz archive",
}

_YAML_LINE = re.compile(r"(---|- |[A-Za-z_\"'][^,]*:(\s|$))")


def _formats_for(kind: str) -> tuple[str, ...]:
    return tuple(f for f, kinds in EXPECTED_KINDS.items() if kind in kinds)


def _text(head: bytes) -> Sniffed | None:
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.start < len(head) - 4:  # not a character cut at the end of the head
            return None
        text = head[: exc.start].decode("utf-8")
    text = text.removeprefix("\ufeff")
    lines = [ln.strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln and not ln.startswith("#")]
    if not lines:
        return None
    first = lines[0]
    if first[0] in "{[":
        return Sniffed("json", "JSON text", _formats_for("json"))
    cells = [c.strip().strip("\"'").lower() for c in first.split(",")]
    if len(cells) >= 3 and {"x", "y", "z"} <= set(cells):
        return Sniffed("csv", "a CSV table (header " + ",".join(cells[:8]) + ")", ("csv",))
    if _YAML_LINE.match(first):
        return Sniffed("yaml", "YAML text", _formats_for("yaml"))
    return None


def sniff(path: Path) -> Sniffed | None:
    """What the file at ``path`` looks like from its first bytes, or None when unsure."""
    try:
        with Path(path).open("rb") as fh:
            head = fh.read(_HEAD)
    except OSError:
        return None  # the reader says why
    if head.startswith(b"\x89HDF\r\n\x1a\n"):
        return Sniffed("hdf5", "an HDF5 file", ("acronym",))
    if head.startswith(b"\x93NUMPY"):
        return Sniffed("npy", "a NumPy .npy array", _formats_for("npy"))
    if head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        return Sniffed("zip", "a zip archive (a NumPy .npz)", _formats_for("zip"))
    if len(head) >= 2 and head[0] == 0x80 and 2 <= head[1] <= 5:
        return Sniffed("pickle", "a Python pickle", ())
    return _text(head)


def check_format(path: Path, fmt: str) -> None:
    """Refuse a file that plainly is not what ``fmt`` reads, naming what it is.

    Raises:
        InputError: ``"<path>: format <fmt> reads <...>, but this is <kind>; use
            format: <formats>"`` (a pickle: save the arrays with NumPy).
    """
    expected = EXPECTED_KINDS.get(fmt)
    found = sniff(path)
    if expected is None or found is None or found.kind in expected:
        return
    if found.formats:
        *most, last = found.formats
        hint = "use format: " + (f"{', '.join(most)} or {last}" if most else last)
    else:
        hint = "no grasp format reads it; save the grasps with numpy.save / numpy.savez"
    raise InputError(
        f"{path}: format {fmt} reads {_WHAT[fmt]}, but this is {found.description}; {hint}",
        path=path,
        value=found.kind,
        choices=found.formats,
    )
