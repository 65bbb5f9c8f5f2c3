r"""``grasps.csv`` text in C++: cells formatted and files split by Arrow, the same text as Python's.

The grasp table's CSV is written and read here in bulk, column by column,
with :mod:`pyarrow.compute` and :mod:`pyarrow.csv` (a million rows in a few
seconds instead of about 40 us per row in Python). The text is exactly what
the Python code writes and accepts:

- **floats**: :func:`repr` text (NaN an empty cell). Arrow's cast to text
  gives the same shortest round-trip digits as :func:`repr` but another
  layout (``1`` for ``1.0``, ``3.2e-9`` for ``3.2e-09``, ``1e+15`` for
  ``1000000000000000.0``). A cell keeps Arrow's text where the layouts agree
  (a fraction between 1e-4 and 1e16), gets its exponent padded to two digits
  (below 1e-4 or from 1e16 on), ``.0`` appended (a whole number under 1e16),
  and :func:`repr` for any other (inf, 1e-5 .. 1e-4, whole numbers past
  1e10 that Arrow writes with an exponent); NaN is ``""``. :func:`arrow_floats_ok` checks
  these rules once per process on values of every kind and falls back to
  :func:`repr` for every cell if they do not hold.
- **reading**: a file is split by Arrow only when it has no ``\r``, its
  header names every column once and every row has the header's fields.
  Without ``"`` Python's :mod:`csv` and Arrow agree on such a file. With
  quotes (text with commas, quotes or newlines), Arrow splits it quoting
  as the writer quotes, and the file is kept only if it is, byte for byte,
  the writer's quoting of the cells Arrow found (each cell quoted exactly
  when it holds ``,``, ``"``, a newline or ``\r``, inner quotes doubled):
  Python's reader reads that text back as those cells. Each cell
  is then converted only where the conversion is exactly Python's (see
  :class:`ArrowCells`). Anything else, and every file with a fault, goes to
  the Python reader, whose errors name the line and the column.
"""

from __future__ import annotations

import functools
import mmap
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from gcm_pipeline.bounds import MAX_CSV_CELL

__all__ = [
    "ArrowCells",
    "Fallback",
    "arrow_floats_ok",
    "bool_cells",
    "empty_cells",
    "float_cells",
    "int_cells",
    "read_text_columns",
    "text_cells",
    "write_rows",
]

#: Rows joined into text at a time (about 40 MB of text for the Panda's columns).
CHUNK_ROWS = 65_536

#: An integer cell as the Python reader takes one.
INT_PATTERN = r"^-?[0-9]{1,18}$"


class Fallback(Exception):
    """The fast reader cannot vouch for a file or cell: read it with Python's :mod:`csv`."""


# ------------------------------------------------------------------ writing


def float_cells(values: np.ndarray, repr_cells: Callable[[np.ndarray], list[str]]) -> Any:
    """Floats as their :func:`repr` text, NaN as ``""`` (an Arrow string array).

    ``repr_cells`` is the Python formatter (``format_floats``): used for the
    cells whose Arrow layout is not :func:`repr`'s, and for every cell when
    :func:`arrow_floats_ok` is false.
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    x = np.ascontiguousarray(values, dtype=float).reshape(-1)
    if not arrow_floats_ok(repr_cells):
        return pa.array(repr_cells(x), type=pa.string())
    return _arrow_floats(x, repr_cells, pa, pc)


def _arrow_floats(x: np.ndarray, repr_cells: Callable[[np.ndarray], list[str]], pa, pc) -> Any:
    """:func:`float_cells` by Arrow's cast with the layout fixed (module docstring)."""
    text = pc.cast(pa.array(x, type=pa.float64()), pa.string())
    has_e = pc.match_substring(text, "e").to_numpy(zero_copy_only=False)
    has_dot = pc.match_substring(text, ".").to_numpy(zero_copy_only=False)
    finite = np.isfinite(x)
    ax = np.abs(x)
    with np.errstate(invalid="ignore"):
        fraction = has_dot & ~has_e & finite & (ax >= 1e-4)  # 0.000123, 12.5: repr's layout
        exponent = has_e & finite & (ax != 0) & ((ax < 1e-4) | (ax >= 1e16))  # 3.2e-9
        whole = ~has_dot & ~has_e & finite & (ax < 1e16)  # 12, 0, -0
    nan = np.isnan(x)
    other = ~(fraction | exponent | whole | nan)  # inf, 1e-5..1e-4, 1.5e+10 ...
    if exponent.any():  # repr writes at least two exponent digits
        text = pc.replace_substring_regex(text, r"e([-+])([0-9])$", r"e\10\2")
    if whole.any():  # repr writes whole numbers with ".0"
        text = pc.if_else(pa.array(whole), pc.binary_join_element_wise(text, ".0", ""), text)
    if other.any():
        fixed = pa.array(repr_cells(x[other]), type=pa.string())
        text = pc.replace_with_mask(text, pa.array(other), fixed)
    if nan.any():
        text = pc.if_else(pa.array(nan), "", text)
    return text


#: Values of every layout :func:`_arrow_floats` handles, checked against repr once.
_PROBES = (
    [0.1, 0.5, 1 / 3, -2.5, 123.456, 0.00012345, 1e-4, 9.999999999999999e-05, 1e-5, 3.2e-9]
    + [1e-300, 5e-324, 2.2250738585072014e-308, -1e-310, 1.7976931348623157e308, 1e16]
    + [9999999999999998.0, 123456789012345.6, 1e15, 2.0**53, 1e22, 1.5e10, 1e9, 0.0, -0.0]
    + [1.0, -7.0, 1e100, -3e-100, float("inf"), float("-inf"), float("nan")]
)


@functools.cache
def _arrow_floats_ok(repr_cells: Callable[[np.ndarray], list[str]]) -> bool:
    import pyarrow as pa
    import pyarrow.compute as pc

    rng = np.random.default_rng(0)
    bits = rng.integers(0, 2**63, size=4096, dtype=np.int64).view(np.float64)
    scaled = rng.random(4096) * 10.0 ** rng.integers(-20, 20, size=4096)
    x = np.concatenate([np.array(_PROBES), bits, scaled, -scaled])
    try:
        return _arrow_floats(x, repr_cells, pa, pc).to_pylist() == repr_cells(x)
    except (pa.ArrowException, ValueError, TypeError):  # pragma: no cover - old Arrow
        return False


def arrow_floats_ok(repr_cells: Callable[[np.ndarray], list[str]]) -> bool:
    """Whether this Arrow's float text, fixed as the module docstring says, is :func:`repr`'s.

    Checked once per process on values of every layout and 12,000 random ones.
    """
    return _arrow_floats_ok(repr_cells)


def int_cells(values: np.ndarray) -> Any:
    """Integers (as int64) as decimal text."""
    import pyarrow as pa
    import pyarrow.compute as pc

    ints = np.ascontiguousarray(values, dtype=np.int64).reshape(-1)
    return pc.cast(pa.array(ints, type=pa.int64()), pa.string())


def bool_cells(values: np.ndarray) -> Any:
    """Booleans as ``true`` / ``false``."""
    import pyarrow as pa
    import pyarrow.compute as pc

    flags = np.ascontiguousarray(values, dtype=bool).reshape(-1)
    return pc.if_else(pa.array(flags, type=pa.bool_()), "true", "false")


def text_cells(values: np.ndarray, quote: Callable[[str], str]) -> Any:
    """Text cells, each ``quote(str(value))`` (each distinct value quoted once)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    arr = np.asarray(values).reshape(-1)
    if arr.dtype.kind != "U" or _inner_nul(arr):  # bytes, objects: str() of each, as Python
        return pa.array([quote(str(s)) for s in arr.tolist()], type=pa.string())
    coded = pc.dictionary_encode(pa.array(arr, type=pa.string()))
    quoted = pa.array([quote(s) for s in coded.dictionary.to_pylist()], type=pa.string())
    return pc.take(quoted, coded.indices)


def _inner_nul(arr: np.ndarray) -> bool:
    """Whether a ``<U`` string holds a NUL before its end (Arrow's conversion cuts it there)."""
    if arr.dtype.itemsize == 0 or len(arr) == 0:
        return False
    codes = np.ascontiguousarray(arr).view(np.uint32).reshape(len(arr), -1)
    # a NUL with a character after it (numpy pads strings with NULs at the end only)
    return bool(((codes[:, :-1] == 0) & (codes[:, 1:] != 0)).any())


def empty_cells(n: int) -> Any:
    """``n`` empty cells (a column the table does not have)."""
    import pyarrow as pa

    return pa.array([""], type=pa.string()).take(np.zeros(n, dtype=np.int64))


def write_rows(fh: BinaryIO, columns: Sequence[Any]) -> None:
    r"""Write the rows of equal-length Arrow text columns: cells joined by ``,``, rows by ``\n``."""
    fh.write(_joined_rows(columns))


def _joined_rows(columns: Sequence[Any]) -> memoryview:
    r"""The text of equal-length Arrow text columns' rows: cells joined by ``,``, rows by ``\n``."""
    import pyarrow as pa
    import pyarrow.compute as pc

    if not columns or len(columns[0]) == 0:
        return memoryview(b"")
    text = pa.large_string()  # 64-bit offsets: any length of text
    wide = [c.cast(text) for c in columns]
    empty, newline, comma = (pa.scalar(s, text) for s in ("", "\n", ","))
    last = pc.binary_join_element_wise(wide[-1], empty, newline)  # the cell, then the newline
    rows = pc.binary_join_element_wise(*wide[:-1], last, comma) if len(wide) > 1 else last
    offsets = np.frombuffer(rows.buffers()[1], dtype=np.int64)
    first, end = int(offsets[rows.offset]), int(offsets[rows.offset + len(rows)])
    return memoryview(rows.buffers()[2])[first:end]


# ------------------------------------------------------------------ reading


def read_text_columns(path: Path) -> tuple[list[str], dict[str, Any]] | None:
    r"""The header and the text of every column of a CSV file, split by Arrow; None: use Python.

    Only for a file Python's :mod:`csv` reads the same way: no ``\r``, no
    NUL, a header without quotes on the first line (after a UTF-8 byte order
    mark) that names every column once, UTF-8 cells of at most
    :data:`~gcm_pipeline.bounds.MAX_CSV_CELL` bytes and the header's number
    of fields in every non-empty line; a file with quotes must be the
    writer's quoting of its cells (module docstring). An empty cell is null.
    """
    import pyarrow as pa
    import pyarrow.csv as pv

    try:
        with path.open("rb") as fh:
            if path.stat().st_size == 0:
                return None
            with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
                if any(mm.find(c) >= 0 for c in (b"\r", b"\0")):
                    return None
                start = 3 if mm[:3] == b"\xef\xbb\xbf" else 0
                end = mm.find(b"\n", start)
                if end < 0:
                    return None
                quoted = mm.find(b'"') >= 0
                names = mm[start:end].decode("utf-8").split(",")
    except (OSError, ValueError):  # unreadable, not UTF-8: the Python reader says why
        return None
    if quoted and any('"' in n for n in names):
        return None
    if len(set(names)) != len(names) or not all(n.strip() for n in names):
        return None
    if max(map(len, names)) > MAX_CSV_CELL:
        return None
    # one thread: the callers' own workers (forked after a read) share the cores
    read = pv.ReadOptions(skip_rows=1, column_names=names, block_size=1 << 22, use_threads=False)
    convert = pv.ConvertOptions(
        column_types={n: pa.string() for n in names}, null_values=[""], strings_can_be_null=True
    )
    try:
        with pa.memory_map(str(path)) as source:
            table = pv.read_csv(
                source,
                read_options=read,
                parse_options=pv.ParseOptions(
                    quote_char='"' if quoted else False,
                    double_quote=True,
                    newlines_in_values=quoted,
                    ignore_empty_lines=True,
                ),
                convert_options=convert,
            )
        if quoted and not _written_as(path, end + 1, table):
            return None
    except (pa.ArrowException, OSError):  # a row of another width, bad UTF-8: Python says where
        return None
    columns = {n: table.column(n) for n in names}
    if table.num_rows and _longest(columns.values()) > MAX_CSV_CELL:
        return None
    return names, columns


def _written_as(path: Path, start: int, table: Any) -> bool:
    r"""Whether the file from byte ``start`` on is exactly the writer's text of ``table``'s rows.

    The writer's text: each cell quoted when it holds ``,``, ``"``, a
    newline or ``\r`` (inner quotes doubled), cells joined by ``,``, every
    row ended by a newline (an empty cell is null in ``table``).
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    text = pa.large_string()
    special = [_has_special(col) for col in table.columns]  # cells to look at one by one
    with path.open("rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        pos = start
        for batch in table.to_batches(max_chunksize=CHUNK_ROWS):
            cells = [c.cast(text).fill_null("") for c in batch.columns]
            cells = [_quoted(c, pa, pc) if q else c for c, q in zip(cells, special, strict=True)]
            body = _joined_rows(cells)
            if mm[pos : pos + len(body)] != body.tobytes():
                return False
            pos += len(body)
        return pos == len(mm)


def _has_special(column: Any) -> bool:
    """Whether any cell of an Arrow text column holds ``,``, ``"`` or a newline (bytes searched)."""
    import pyarrow as pa

    for chunk in column.chunks:
        if len(chunk) == 0:
            continue
        wide = chunk.type in (pa.large_string(), pa.large_binary())
        offsets = np.frombuffer(chunk.buffers()[1], dtype=np.int64 if wide else np.int32)
        first, end = int(offsets[chunk.offset]), int(offsets[chunk.offset + len(chunk)])
        data = chunk.buffers()[2]
        text = b"" if data is None else memoryview(data)[first:end].tobytes()
        if any(text.find(c) >= 0 for c in (b",", b'"', b"\n")):
            return True
    return False


def _quoted(cells: Any, pa: Any, pc: Any) -> Any:
    """Text cells as the writer quotes them (``grasps_csv._quote``), in Arrow."""
    needs = pc.match_substring_regex(cells, '[,"\n\r]')
    if not pc.any(needs).as_py():
        return cells
    quote, empty = pa.scalar('"', cells.type), pa.scalar("", cells.type)
    inner = pc.replace_substring(cells, '"', '""')
    return pc.if_else(needs, pc.binary_join_element_wise(quote, inner, quote, empty), cells)


def _longest(columns: Any) -> int:
    import pyarrow.compute as pc

    return max(int(pc.max(pc.binary_length(c)).as_py() or 0) for c in columns)


class ColumnsByType:
    """:meth:`parse` of the two ``grasps.csv`` readers (Arrow's and Python's cells).

    A subclass has ``n`` rows and the methods ``floats``, ``ints``,
    ``switches`` and ``text`` of one column name each.
    """

    n: int
    floats: Callable[[str], np.ndarray]
    ints: Callable[[str], np.ndarray]
    switches: Callable[[str], np.ndarray]
    text: Callable[[str], np.ndarray]

    def parse(self, names: list[str], dtype: str) -> np.ndarray:
        """The cells ``names`` as one (N,) column or (N, len(names)) by the registry's dtype."""
        read = {"float": self.floats, "int": self.ints, "bool": self.switches, "str": self.text}
        parts = [read[dtype](c) for c in names]
        if len(parts) == 1:
            return parts[0]
        return np.column_stack(parts).reshape(self.n, len(parts))


class ArrowCells(ColumnsByType):
    """The text columns of :func:`read_text_columns`, converted as the Python reader converts.

    The columns are Arrow text (an empty cell null). The methods match the
    Python reader's (``_Cells`` of :mod:`~gcm_pipeline.rundir.grasps_csv`);
    where Arrow could differ from Python (a ``nan`` text, a cell
    Arrow does not parse), they raise :class:`Fallback` (the whole file is
    read again by Python) or convert with the Python code (:meth:`column`).
    """

    def __init__(self, path: Path, header: list[str], columns: dict[str, Any]):
        self.path, self.header, self.raw = path, header, columns
        self.n = len(next(iter(columns.values()))) if columns else 0

    @property
    def lines(self) -> list[int]:
        """The line of each row: not known here, so a fault's message comes from Python's reader."""
        raise Fallback("a fault in the file")

    def bad(self, name: str, i: int, what: str) -> Exception:
        """A fault in a cell: the Python reader reads the file again and names it."""
        raise Fallback(f"{name}:{i}: {what}")

    def floats(self, name: str) -> np.ndarray:
        """A float column (an empty cell is NaN); a ``nan`` or odd cell: :class:`Fallback`."""
        values = self._floats(name)
        if values is None:
            raise Fallback(name)
        return values

    def _floats(self, name: str) -> np.ndarray | None:
        import pyarrow as pa
        import pyarrow.compute as pc

        col = self.raw[name]
        try:
            values = pc.cast(col, pa.float64())
        except pa.ArrowInvalid:  # not Arrow's number: Python's (" 1", "1_0") or an error
            return None
        out = values.to_numpy(zero_copy_only=False)  # a null is NaN
        if values.null_count < len(values) - int(np.count_nonzero(~np.isnan(out))):
            return None  # a "nan" text: Python's float decides its sign
        return out

    def ints(self, name: str) -> np.ndarray:
        """An integer column (no empty cells), ``-?[0-9]{1,18}`` as Python checks."""
        values = self._ints(name)
        if values is None:
            raise Fallback(name)
        return values

    def _ints(self, name: str) -> np.ndarray | None:
        import pyarrow as pa
        import pyarrow.compute as pc

        col = self.raw[name]
        if col.null_count or not pc.all(pc.match_substring_regex(col, INT_PATTERN)).as_py():
            return None
        return pc.cast(col, pa.int64()).to_numpy(zero_copy_only=False).reshape(self.n)

    def switches(self, name: str) -> np.ndarray:
        """A boolean column of ``true`` / ``false`` cells."""
        values = self._switches(name)
        if values is None:
            raise Fallback(name)
        return values

    def _switches(self, name: str) -> np.ndarray | None:
        import pyarrow.compute as pc

        col = self.raw[name]
        if col.null_count or not pc.all(pc.is_in(col, value_set=_SWITCHES())).as_py():
            return None
        return pc.equal(col, "true").to_numpy(zero_copy_only=False).astype(bool).reshape(self.n)

    def text(self, name: str) -> np.ndarray:
        """A string column (``<U`` as wide as its longest cell)."""
        import pyarrow.compute as pc

        coded = pc.dictionary_encode(self.raw[name].fill_null("").combine_chunks())
        words = np.array(coded.dictionary.to_pylist(), dtype=str)
        return words[coded.indices.to_numpy(zero_copy_only=False)].reshape(self.n)

    def column(self, name: str, parse: Callable[[Any], np.ndarray]) -> np.ndarray:
        """A further column: bool, int, float (empty = NaN) or text, as Python's ``parse``."""
        if self.n:
            for read in (self._switches, self._ints):
                values = read(name)
                if values is not None:
                    return values
        values = self._floats(name)
        if values is not None:
            return values
        return parse(self.raw[name].fill_null("").to_numpy(zero_copy_only=False))


@functools.cache
def _SWITCHES() -> Any:  # noqa: N802 - a constant built on first use
    import pyarrow as pa

    return pa.array(["true", "false"], type=pa.string())
