"""One line per invalid YAML value: the formatter shared by every config front-end.

Run configs (:mod:`~gcm_pipeline.config.run`), study files
(:mod:`~gcm_pipeline.config.study`) and robot specs with their tools
(:mod:`~gcm_pipeline.config.robot_spec`) report a bad value the same way:
the dotted key path, the value at fault (quoted with
:func:`~gcm_pipeline.errors.clip`) and, for a closed set, the valid keys or
values and the closest one. Where the YAML reader knows it
(:mod:`~gcm_pipeline.safe_yaml`), the file's line and column come first.

:func:`describe` turns the first error of a pydantic ``ValidationError`` into
a :class:`Problem`; :func:`unknown_key` is the message of a key outside a
section, for the front-ends that check keys by hand.
"""

from __future__ import annotations

import difflib
import re
import types
import typing
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from gcm_pipeline.errors import ConfigError, clip, unknown_choice

__all__ = ["Problem", "describe", "dotted", "unknown_key", "validated_file"]

M = TypeVar("M", bound=BaseModel)

#: A front-end's own wording for some errors: (error, dotted key, location) -> message or None.
Special = Callable[[dict[str, Any], str, list[Any]], "str | None"]


@dataclass(frozen=True)
class Problem:
    """The first validation error of a document, as evidence and one line.

    Attributes:
        key: Dotted key of the value at fault (``environment.table.size.0``; ``''``
            for the document itself).
        loc: The same as keys and list indices.
        message: One line naming the key, the value and, for a closed set, the choices.
        kind: pydantic's error type (``extra_forbidden``, ``missing``, ...).
        value: The value at fault as given (for an unknown key: the key; None
            for a missing one).
        choices: The valid values (or, for an unknown key, the section's keys),
            sorted; None where the set is open.
    """

    key: str
    loc: tuple[Any, ...]
    message: str
    kind: str
    value: Any = None
    choices: tuple[str, ...] | None = None

    def error(self, message: str) -> ConfigError:
        """A :class:`~gcm_pipeline.errors.ConfigError` with ``message`` and this evidence.

        Args:
            message: The line to print (the caller's prefix, e.g. the file, and
                :attr:`message`).
        """
        return ConfigError(message, key=self.key or None, value=self.value, choices=self.choices)


def dotted(loc: Iterable[Any], *, brackets: bool = False) -> str:
    """A location as a dotted key: ``('sweep', 'objects', 0)`` -> ``sweep.objects.0``.

    With ``brackets`` list indices are ``sweep.objects[0]``.
    """
    if not brackets:
        return ".".join(str(p) for p in loc)
    return "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc).lstrip(".")


def unknown_key(parent: str, key: Any, valid: Sequence[str], noun: str = "key") -> str:
    """The message of a key that a section does not have.

    Args:
        parent: Dotted path of the section (``''`` at the top of the file).
        key: The key given.
        valid: The section's keys.
        noun: What the keys are (``pose key``).

    Returns:
        ``unknown <noun> '<parent.key>' (did you mean '<parent.close>'?); valid
        keys here: a, b, c``.
    """
    names = sorted(str(v) for v in valid)
    full = f"{parent}.{key}" if parent else str(key)
    close = difflib.get_close_matches(str(key), names, n=1)
    hint = f" (did you mean {(f'{parent}.{close[0]}' if parent else close[0])!r}?)" if close else ""
    return f"unknown {noun} {clip(full)}{hint}; valid keys here: {', '.join(names)}"


def validated_file(
    raw: Any,
    model: type[M],
    where: str,
    error: type[Exception],
    special: Special | None = None,
) -> M:
    """A spec file's document (robot, gripper) validated by ``model``, or one line.

    Args:
        raw: The document as read from YAML.
        model: The file's pydantic model.
        where: What the message names first (the file).
        error: The error type to raise.
        special: A front-end's own wording (:func:`describe`).

    Raises:
        error: ``<where>: <key>: <problem>`` (list indices in brackets), or a
            document that is not a mapping.
    """
    if not isinstance(raw, dict):
        raise error(f"{where}: expected a mapping at the top level, got {clip(raw)}")
    try:
        return model.model_validate(raw)
    except ValidationError as exc:
        problem = describe(exc, raw, model, special=special, brackets=True)
        raise error(f"{where}: {problem.message}") from None


def describe(
    exc: ValidationError,
    data: Any,
    model: type[BaseModel],
    *,
    special: Special | None = None,
    brackets: bool = False,
) -> Problem:
    """The first error of ``model.model_validate(data)`` as one line.

    Of a union's branches, the error of the branch that matches the input's
    type is reported (a list given for ``list | Model`` reports the list's
    error). Union members and validator tags are left out of the key.

    Args:
        exc: The error pydantic raised.
        data: The document that was validated (plain data).
        model: The model it was validated against (for valid keys and tuple sizes).
        special: A front-end's own wording for some errors (return None to
            fall back to the common one).
        brackets: Write list indices as ``tool.collision[1]`` (default ``tool.collision.1``).

    Returns:
        The problem; its message does not name the file (the caller prefixes it).
    """
    errors = exc.errors(include_url=False)
    err = _pick(errors)
    if err["type"] == "missing":
        # a misspelt key is both unknown and missing: name the unknown one (its
        # message suggests the key meant), not only the missing one
        typo = [
            e
            for e in errors
            if e["type"] == "extra_forbidden" and tuple(e["loc"][:-1]) == tuple(err["loc"][:-1])
        ]
        err = typo[0] if typo else err
    loc = _data_loc(data, list(err["loc"]), keep_last=err["type"] == "missing")
    key = dotted(loc, brackets=brackets)
    message = None if special is None else special(err, key, loc)
    if message is None:
        message = _common(err, key, loc, data, model, brackets)
    value, choices = _evidence(err, loc, model)
    return Problem(key, tuple(loc), message, err["type"], value, choices)


def _evidence(
    err: dict[str, Any], loc: list[Any], model: type[BaseModel]
) -> tuple[Any, tuple[str, ...] | None]:
    """The value at fault and the valid choices (None where open) of an error."""
    kind = err["type"]
    if kind == "extra_forbidden" and loc:
        return loc[-1], tuple(sorted(_valid_keys(model, loc[:-1])[0]))
    if kind == "literal_error":
        return err.get("input"), tuple(sorted(_literal_choices(err)))
    if kind == "missing":
        return None, None
    return err.get("input"), None


def _valid_keys(model: type[BaseModel], loc: list[Any]) -> tuple[list[str], str]:
    """The keys of the section at ``loc`` and what they are called (``key``, ``pose key``)."""
    at = _model_at(model, loc)
    if at is None:
        return [], "key"
    return [f.alias or n for n, f in at.model_fields.items()], getattr(at, "key_noun", "key")


def _literal_choices(err: dict[str, Any]) -> list[str]:
    """The values a ``literal_error`` allows."""
    return re.findall(r"'([^']*)'", str(err.get("ctx", {}).get("expected", "")))


def _common(
    err: dict[str, Any],
    key: str,
    loc: list[Any],
    data: Any,
    model: type[BaseModel],
    brackets: bool = False,
) -> str:
    kind = err["type"]
    if kind == "extra_forbidden" and loc:
        valid, noun = _valid_keys(model, loc[:-1])
        return unknown_key(dotted(loc[:-1], brackets=brackets), loc[-1], valid, noun)
    if kind == "missing" and loc and isinstance(loc[-1], int):
        # a tuple with too few values: pydantic reports the first missing index
        parent = dotted(loc[:-1], brackets=brackets)
        got = _value_at(data, loc[:-1])
        n = len(got) if isinstance(got, (list, tuple)) else "?"
        return f"{parent}: expected {_tuple_len(model, loc[:-1])} values, got {n} ({clip(got)})"
    if kind == "missing":
        return f"missing required key {clip(key)}"
    if kind == "too_short":
        return f"{key}: empty list; give at least one value"
    if kind == "too_long":
        got, most = err["input"], err.get("ctx", {}).get("max_length")
        size = _tuple_len(model, loc)
        if size == "?" and most is not None:  # a list with a bound
            return f"{key}: at most {most:,} items, got {len(got):,}"
        return f"{key}: expected {size} values, got {len(got)} ({clip(got)})"
    if kind == "literal_error":
        return f"{key}: " + unknown_choice("value", err["input"], _literal_choices(err))
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        got = err.get("input")
        return (
            f"{key or 'config'}: expected a mapping of keys, got {type(got).__name__} {clip(got)}"
        )
    msg = err["msg"].removeprefix("Value error, ")
    if key and "input" in err and kind != "value_error":  # a validator's message says it all
        return f"{key}: {msg} (got {clip(err['input'])})"
    return f"{key}: {msg}" if key else msg


def _pick(errors: list[Any]) -> Any:
    """The error to report: of a union's branches, the one matching the input's type."""
    first = errors[0]
    prefix: dict[type, str] = {list: "list[", dict: ""}
    branch = prefix.get(type(first.get("input")))
    if branch is None:
        return first
    for err in errors:
        tags = [p for p in err["loc"] if isinstance(p, str) and (p[:1].isupper() or "[" in p)]
        if not tags:
            continue
        if (branch == "list[") == any(t.startswith("list[") for t in tags) and (
            branch == "list[" or not any(t.startswith(("literal[", "list[")) for t in tags)
        ):
            return err
    return first


def _data_loc(data: Any, loc: list[Any], *, keep_last: bool) -> list[Any]:
    """The parts of a pydantic error location that walk through ``data``.

    pydantic puts union members and validator tags (``ObjectConfig``, ``int``,
    ``function-after[...]``) into a location: only the keys and indices of the
    data are kept (and a missing key, which the data cannot have).
    """
    node, out = data, []
    for i, part in enumerate(loc):
        if isinstance(node, dict) and isinstance(part, (str, int)) and part in node:
            node = node[part]
        elif isinstance(node, list) and isinstance(part, int) and 0 <= part < len(node):
            node = node[part]
        elif not (keep_last and i == len(loc) - 1):
            continue
        out.append(part)
    return out


def _value_at(data: Any, loc: list[Any]) -> Any:
    """The raw input value at a location path (None where it leaves the data)."""
    node = data
    for part in loc:
        try:
            node = node[part]
        except (KeyError, IndexError, TypeError):
            return None
    return node


def _tuple_len(model: type[BaseModel], loc: list[Any]) -> int | str:
    """How many values the tuple field at ``loc`` takes ('?' if not a fixed tuple)."""
    at = _model_at(model, loc[:-1])
    if at is None or not loc or not isinstance(loc[-1], str) or loc[-1] not in at.model_fields:
        return "?"
    ann = at.model_fields[loc[-1]].annotation
    for arg in (ann, *typing.get_args(ann)):
        if typing.get_origin(arg) is tuple:
            args = typing.get_args(arg)
            if args and args[-1] is not Ellipsis:
                return len(args)
    return "?"


def _models_in(ann: Any, depth: int = 0) -> list[type[BaseModel]]:
    """The models an annotation holds: through Optional, unions, Annotated, tuples, lists."""
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        return [ann]
    if depth > 4:
        return []
    origin = typing.get_origin(ann)
    if origin in (typing.Union, types.UnionType, typing.Annotated, tuple, list):
        args = typing.get_args(ann)[:1] if origin is typing.Annotated else typing.get_args(ann)
        return [m for a in args for m in _models_in(a, depth + 1)]
    return []


def _model_at(model: type[BaseModel], loc: list[Any]) -> type[BaseModel] | None:
    """Follow a location path through nested models; None where it leaves them."""
    current: type[BaseModel] | None = model
    for part in loc:
        if isinstance(part, int):
            continue
        if current is None:
            return None
        fields = {f.alias or n: f for n, f in current.model_fields.items()}
        field = fields.get(str(part)) or current.model_fields.get(str(part))
        if field is None:
            return None
        models = _models_in(field.annotation)
        current = models[0] if models else None
    return current
