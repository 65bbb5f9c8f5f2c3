"""A YAML reader for untrusted files: bounded size, depth and alias expansion, no duplicate keys.

Configs, ``--set`` values and robot specs are read with :func:`load_yaml` /
:func:`read_yaml_file`, PyYAML's safe loader with these limits:

=============================== ==============================================
limit                           why
=============================== ==============================================
``MAX_YAML_BYTES`` (1 MiB)      a config or spec is a few kB; larger is not one
``MAX_YAML_DEPTH`` (64)         nesting deeper than any section (the composer
                                recurses: 3,000 levels overflow the stack)
``MAX_YAML_VALUES`` (100,000)   values after alias expansion (``&a`` / ``*a``):
                                nested aliases ("billion laughs") expand
                                exponentially once validated or printed
duplicate keys                  YAML says keys are unique; PyYAML keeps the
                                last one silently
=============================== ==============================================

Numbers: YAML 1.2 floats without a dot (``1e-4``) are floats here, as a
reader of a config expects (PyYAML alone reads them as strings).

Every problem raises the error class the caller passes (a
:class:`~gcm_pipeline.errors.GcmError` subclass) with one line naming the
source, line and column.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Any

import yaml
from yaml.nodes import MappingNode, Node, SequenceNode

from gcm_pipeline.errors import GcmError

__all__ = [
    "MAX_YAML_BYTES",
    "MAX_YAML_DEPTH",
    "MAX_YAML_VALUES",
    "load_yaml",
    "read_yaml_file",
]

MAX_YAML_BYTES = 1 << 20
MAX_YAML_DEPTH = 64
MAX_YAML_VALUES = 100_000

_MERGE_TAG = "tag:yaml.org,2002:merge"


class _Limit(yaml.YAMLError):
    """A limit of this module was hit (carries the mark of the node at fault)."""

    def __init__(self, problem: str, mark: Any) -> None:
        super().__init__(problem)
        self.problem = problem
        self.problem_mark = mark


class _UniqueKeys:
    """Constructor part of both loaders: unique mapping keys."""

    construct_object: Any  # yaml's constructor method, next in the loaders' MRO

    def construct_mapping(self, node: MappingNode, deep: bool = False) -> dict[Any, Any]:  # noqa: D102
        seen: dict[Any, Any] = {}
        for key_node, _ in node.value:
            if key_node.tag == _MERGE_TAG:
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                first = seen.setdefault(key, key_node.start_mark)
            except TypeError:
                continue  # unhashable: the constructor reports it
            if first is not key_node.start_mark:
                raise _Limit(
                    f"duplicate key {_short(key)} (first at line {first.line + 1})",
                    key_node.start_mark,
                )
        return super().construct_mapping(node, deep=deep)  # type: ignore[misc]

    def construct_yaml_int(self, node: Node) -> int:  # noqa: D102
        try:
            return super().construct_yaml_int(node)  # type: ignore[misc]
        except ValueError:  # Python's limit of digits in an int (4,300)
            most = sys.get_int_max_str_digits()
            raise _Limit(
                f"an integer of {len(node.value):,} digits (at most {most:,})", node.start_mark
            ) from None


class _Loader(_UniqueKeys, yaml.SafeLoader):
    """``yaml.SafeLoader`` with a depth limit, unique keys and YAML 1.2 floats."""

    def __init__(self, stream: Any) -> None:
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent: Node | None, index: Any) -> Node | None:  # noqa: D102
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH:
                mark = self.peek_event().start_mark
                raise _Limit(f"nested deeper than {MAX_YAML_DEPTH} levels", mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


#: libyaml's parser and composer (C), the same constructor and resolver: for
#: large documents (grasp files), where the pure-Python parser takes seconds.
#: Its composer cannot be given the depth limit, so :func:`_check_depth` runs
#: first, over libyaml's flat event stream.
_CLoader: Any = None
if getattr(yaml, "__with_libyaml__", False):

    class _CLoader(_UniqueKeys, yaml.CSafeLoader):  # type: ignore[no-redef]
        """``yaml.CSafeLoader`` with unique keys and YAML 1.2 floats."""


#: Documents at least this long [characters] use libyaml when it is installed.
FAST_YAML_CHARS = 1 << 16

#: PyYAML's int and float resolvers without their base-60 branch (``1:30`` = 90) and
#: without YAML 1.1's octal ``010`` = 8 (a leading zero makes a string, as ``08`` was).
_YAML12_NUMBERS = {
    "tag:yaml.org,2002:int": re.compile(
        r"^(?:[-+]?0b[0-1_]+|[-+]?(?:0|[1-9][0-9_]*)|[-+]?0x[0-9a-fA-F_]+)$"
    ),
    "tag:yaml.org,2002:float": re.compile(
        r"^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+][0-9]+)?|\.[0-9][0-9_]*(?:[eE][-+][0-9]+)?"
        r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"
    ),
}

# YAML 1.2 floats: also 1e-4, 1E5, 2.5e3 (PyYAML's YAML 1.1 needs a dot and a signed exponent)
for _cls in (_Loader, _CLoader):
    if _cls is not None:
        _cls.add_implicit_resolver(
            "tag:yaml.org,2002:float",
            re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
            list("-+0123456789."),
        )
        _cls.add_constructor("tag:yaml.org,2002:int", _cls.construct_yaml_int)
        # no YAML 1.1 base-60 or leading-zero octal numbers (YAML 1.2 dropped them)
        for _resolvers in _cls.yaml_implicit_resolvers.values():
            _resolvers[:] = [
                (tag, _YAML12_NUMBERS.get(tag, rx) if "(?::[0-5]?[0-9])" in rx.pattern else rx)
                for tag, rx in _resolvers
            ]


def _check_depth(text: str) -> None:
    """Raise :class:`_Limit` where a node lies deeper than ``MAX_YAML_DEPTH`` (libyaml events).

    The same count as :meth:`_Loader.compose_node`: the root node is at depth 1,
    the children of a collection one deeper.
    """
    depth = 0
    for event in yaml.parse(text, Loader=yaml.CSafeLoader):
        if isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
            depth += 1
            if depth > MAX_YAML_DEPTH:
                raise _Limit(f"nested deeper than {MAX_YAML_DEPTH} levels", event.start_mark)
        elif isinstance(event, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
            depth -= 1
        elif isinstance(event, (yaml.ScalarEvent, yaml.AliasEvent)) and depth + 1 > MAX_YAML_DEPTH:
            raise _Limit(f"nested deeper than {MAX_YAML_DEPTH} levels", event.start_mark)


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _expanded_size(root: Node, limit: int = MAX_YAML_VALUES) -> int:
    """Number of values the node graph stands for once aliases are expanded.

    Aliases are shared nodes in the composed graph, so the count is a sum over
    a DAG, memoised per node (linear in the number of distinct nodes). Stops
    counting beyond ``limit``. An alias inside the collection it names
    (``a: &a [*a]``) makes a cycle, an infinite value: :class:`_Limit`.
    """
    memo: dict[int, int] = {}
    open_: set[int] = set()  # nodes whose children are being counted: the current path
    # iterative post-order walk (depth is already bounded, but stay flat)
    stack: list[tuple[Node, bool]] = [(root, False)]
    while stack:
        node, done = stack.pop()
        key = id(node)
        if key in memo:
            continue
        if not done and key in open_:
            raise _Limit("an alias (*) inside the collection its anchor (&) names", node.start_mark)
        children: list[Node]
        if isinstance(node, SequenceNode):
            children = list(node.value)
        elif isinstance(node, MappingNode):
            children = [n for pair in node.value for n in pair]
        else:
            children = []
        if done:
            total = 1 + sum(memo[id(c)] for c in children)
            memo[key] = min(total, limit + 1)
            open_.discard(key)
            continue
        open_.add(key)
        stack.append((node, True))
        stack.extend((c, False) for c in children if id(c) not in memo)
    return memo[id(root)]


def load_yaml(
    text: str,
    source: str,
    error: type[GcmError],
    *,
    plain_on_syntax_error: bool = False,
    max_values: int = MAX_YAML_VALUES,
) -> Any:
    """Parse YAML text within the limits of this module.

    Args:
        text: The YAML document.
        source: What to name in messages (a file path, ``--set key``).
        error: The exception class to raise.
        plain_on_syntax_error: Return ``text`` itself when it is not valid YAML
            syntax (``--set`` values such as ``@x``); the limits still raise.
        max_values: Most values after alias expansion (data files such as
            grasp lists hold more than a config).

    Returns:
        The parsed data (dicts, lists, str, int, float, bool, None, dates).

    Raises:
        error: ``<source>:<line>:<column>: <problem>`` for malformed YAML, a
            duplicate key, nesting deeper than ``MAX_YAML_DEPTH``, or more than
            ``max_values`` values after alias expansion.
    """
    loader = None
    try:
        if _CLoader is not None and len(text) >= FAST_YAML_CHARS:
            _check_depth(text)
            loader = _CLoader(text)
        else:
            loader = _Loader(text)  # reads the first characters: may raise
        node = loader.get_single_node()
        if node is None:
            return None
        if _expanded_size(node, max_values) > max_values:
            raise _Limit(
                f"expands to more than {max_values:,} values through aliases (&/*); "
                "write the values out",
                node.start_mark,
            )
        return loader.construct_document(node)
    except _Limit as exc:
        raise error(_where(source, exc.problem_mark) + str(exc.problem)) from None
    except yaml.MarkedYAMLError as exc:
        if plain_on_syntax_error:
            return text
        raise error(_where(source, exc.problem_mark) + f"malformed YAML: {exc.problem}") from None
    except yaml.YAMLError as exc:
        if plain_on_syntax_error:
            return text
        raise error(f"{source}: malformed YAML: {' '.join(str(exc).split())}") from None
    except RecursionError:  # pragma: no cover - the depth limit comes first
        raise error(f"{source}: YAML nested too deeply") from None
    finally:
        if loader is not None:
            loader.dispose()


def _where(source: str, mark: Any) -> str:
    if mark is None:
        return f"{source}: "
    return f"{source}:{mark.line + 1}:{mark.column + 1}: "


def read_yaml_file(path: str | Path, what: str, error: type[GcmError]) -> Any:
    """Read and parse a YAML file of at most ``MAX_YAML_BYTES`` (UTF-8).

    Args:
        path: The file.
        what: What the file is, for messages (``config``, ``robot spec``).
        error: The exception class to raise.

    Raises:
        error: Missing file, not a file, too large, not UTF-8, or see
            :func:`load_yaml`.
    """
    path = Path(path)
    if not path.exists():
        raise error(f"{what} file not found: {path}")
    if not path.is_file():
        raise error(f"{what} path is not a file: {path}")
    try:
        with path.open("rb") as fh:
            data = fh.read(MAX_YAML_BYTES + 1)
    except OSError as exc:
        raise error(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    if len(data) > MAX_YAML_BYTES:
        raise error(
            f"{path}: a {what} file is at most {MAX_YAML_BYTES // 1024} KiB; this one is larger"
        )
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise error(
            f"{path}:{line}: {what} is not UTF-8 text (byte 0x{data[exc.start]:02x}); "
            "save it as UTF-8"
        ) from None
    return load_yaml(text.removeprefix("\ufeff"), str(path), error)
