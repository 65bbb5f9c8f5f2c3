"""The YAML reader of configs, overrides and robot specs: limits and one-line errors."""

from __future__ import annotations

import math
import time

import pytest
from helpers import FLAT

from gcm_pipeline.config import load_config
from gcm_pipeline.errors import ConfigError, RobotSpecError
from gcm_pipeline.safe_yaml import (
    MAX_YAML_BYTES,
    MAX_YAML_DEPTH,
    MAX_YAML_VALUES,
    load_yaml,
    read_yaml_file,
)


def _load(text: str):
    return load_yaml(text, "src", ConfigError)


def _error(text: str) -> str:
    with pytest.raises(ConfigError) as info:
        _load(text)
    msg = str(info.value)
    assert "\n" not in msg and len(msg) < 300, msg
    return msg


def test_plain_documents_and_yaml12_floats():
    data = _load("a: 1e-4\nb: 1.0e4\nc: 1.5\nd: 3\ne: -2E3\nf: 1e3x\ng: true\nh: null\n")
    assert data == {
        "a": 1e-4,
        "b": 1e4,
        "c": 1.5,
        "d": 3,
        "e": -2000.0,
        "f": "1e3x",
        "g": True,
        "h": None,
    }
    assert isinstance(data["a"], float) and isinstance(data["d"], int)
    assert _load("") is None
    assert _load("- a\n- b\n") == ["a", "b"]
    # anchors and merge keys stay usable
    assert _load("base: &b {x: 1, y: 2}\nc:\n  <<: *b\n  x: 3\n")["c"] == {"x": 3, "y": 2}


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("seed: 1\nseed: 2\n", "src:2:1: duplicate key 'seed' (first at line 1)"),
        ("a: {x: 1, x: 2}\n", "duplicate key 'x'"),
        ("a:\n  b: 1\n  c: 2\n  b: 3\n", "src:4:3: duplicate key 'b'"),
        ("a: [1, 2\n", "malformed YAML"),
        ("? [1]\n: 2\n", "unhashable"),
        ("a: !!python/object:os.system x\n", "could not determine a constructor"),
    ],
)
def test_errors_name_the_line(text, fragment):
    assert fragment in _error(text)


@pytest.mark.parametrize(
    "text",
    [
        "a: " + "[" * 3000 + "]" * 3000,
        "a: " + "{a: " * 3000 + "1" + "}" * 3000,
        "a:\n" + "".join("  " * i + "a:\n" for i in range(1, 200)),
        "".join("- " * 100) + "x\n",
    ],
    ids=["flow-lists", "flow-maps", "block-maps", "block-lists"],
)
def test_deep_nesting_is_refused_without_recursion(text):
    assert f"nested deeper than {MAX_YAML_DEPTH} levels" in _error(text)


def test_alias_bomb_is_refused_at_once():
    names = "abcdefghij"
    bomb = f"{names[0]}: &{names[0]} [x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{names[i + 1]}: &{names[i + 1]} [{', '.join(['*' + names[i]] * 9)}]\n" for i in range(9)
    )
    t0 = time.perf_counter()
    msg = _error(bomb)
    assert time.perf_counter() - t0 < 5.0  # nothing was expanded
    assert f"more than {MAX_YAML_VALUES:,} values through aliases" in msg
    # a handful of aliases is fine
    assert _load("a: &a [1, 2]\nb: [*a, *a]\n") == {"a": [1, 2], "b": [[1, 2], [1, 2]]}


def test_set_values_use_the_same_limits():
    with pytest.raises(ConfigError, match="--set seed:1:8: duplicate key 'a'"):
        load_config(FLAT, ["seed={a: 1, a: 2}"])
    # text that is no YAML syntax is a plain string
    cfg = load_config(FLAT, ["robot.spec=@panda"])
    assert cfg.robot.spec == "@panda"


def test_files_too_large_not_utf8_or_missing(tmp_path):
    big = tmp_path / "big.yaml"
    big.write_bytes(b"# " + b"x" * MAX_YAML_BYTES + b"\n")
    with pytest.raises(ConfigError, match="a config file is at most 1024 KiB"):
        read_yaml_file(big, "config", ConfigError)
    latin = tmp_path / "latin.yaml"
    latin.write_bytes("seed: 0\n# caf\xe9\n".encode("latin-1"))
    with pytest.raises(RobotSpecError, match=r"latin.yaml:2: robot spec is not UTF-8 text"):
        read_yaml_file(latin, "robot spec", RobotSpecError)
    with pytest.raises(ConfigError, match="config file not found"):
        read_yaml_file(tmp_path / "nope.yaml", "config", ConfigError)
    with pytest.raises(ConfigError, match="not a file"):
        read_yaml_file(tmp_path, "config", ConfigError)
    bom = tmp_path / "bom.yaml"
    bom.write_bytes(b"\xef\xbb\xbfseed: 3\n")
    assert read_yaml_file(bom, "config", ConfigError) == {"seed": 3}


_PAD = "# " + "x" * 70_000 + "\n"  # a comment that makes a document large (libyaml's path)


def test_large_documents_read_the_same_through_libyaml(monkeypatch):
    """Large documents (grasp files) are parsed by libyaml: the same data, the same limits."""
    import gcm_pipeline.safe_yaml as sy

    if sy._CLoader is None:
        pytest.skip("PyYAML without libyaml")
    rows = "\n".join(f"  - [{i}, {i}.5, 1e-4, -2.5e3, true, null, 'q{i}']" for i in range(3000))
    text = f"{_PAD}grasps:\n{rows}\nwhen: 2026-12-02\nname: x\nnested: {{a: {{b: [1, 2]}}}}\n"
    assert len(text) >= sy.FAST_YAML_CHARS
    fast = _load(text)
    monkeypatch.setattr(sy, "FAST_YAML_CHARS", 10**12)  # the pure-Python path
    assert _load(text) == fast
    assert fast["grasps"][7] == [7, 7.5, 1e-4, -2500.0, True, None, "q7"]
    monkeypatch.undo()
    # the limits hold on that path too, at the same place
    assert _error(_PAD + "a: 1\nb: 2\na: 3\n").startswith("src:4:1: duplicate key 'a'")
    deep = _PAD + "[" * (MAX_YAML_DEPTH + 6) + "]" * (MAX_YAML_DEPTH + 6)
    assert f"nested deeper than {MAX_YAML_DEPTH} levels" in _error(deep)
    bomb = _PAD + "a: &a [1,2,3,4,5,6,7,8,9]\nb: &b [*a,*a,*a,*a,*a,*a,*a,*a,*a]\n"
    bomb += "c: &c [*b,*b,*b,*b,*b,*b,*b,*b,*b]\nd: &d [*c,*c,*c,*c,*c,*c,*c,*c,*c]\n"
    bomb += "e: [" + ",".join(["*d"] * 20) + "]\n"
    assert "through aliases" in _error(bomb)
    assert "malformed YAML" in _error(_PAD + "[" * 100_000)  # libyaml's own nesting guard


@pytest.mark.parametrize("pad", ["", _PAD])  # the pure-Python and libyaml paths
@pytest.mark.parametrize(
    "text", ["a: &a [*a]\n", "x: &x {y: *x}\n", "a: &a [1, {b: [2, *a]}]\n", "&r [*r]\n"]
)
def test_an_alias_inside_its_own_anchor_is_refused_at_once(text, pad):
    # a recursive value, infinite once expanded: the reader used to loop with memory growing
    t0 = time.perf_counter()
    msg = _error(pad + text)
    assert time.perf_counter() - t0 < 5.0
    assert "an alias (*) inside the collection its anchor (&) names" in msg
    with pytest.raises(ConfigError, match=r"--set seed:1:1: an alias \(\*\) inside"):
        load_config(FLAT, ["seed=&a [*a]"])
    # a shared anchor that is not its own ancestor is fine (a DAG)
    assert _load(pad + "b: &b [1]\nc: [*b, [*b, {d: *b}]]\n")["c"] == [[1], [[1], {"d": [1]}]]


@pytest.mark.parametrize("pad", ["", _PAD])
def test_an_integer_too_long_for_python_is_one_line(pad):
    msg = _error(pad + "candidates: {count: " + "9" * 5000 + "}\n")
    assert msg.startswith(f"src:{2 if pad else 1}:21: an integer of 5,000 digits (at most")
    with pytest.raises(ConfigError, match="--set seed:1:1: an integer of 5,000 digits"):
        load_config(FLAT, ["seed=" + "9" * 5000])
    assert _load(pad + "a: 0x1F\nb: -12_000\nc: 0b101\n") == {"a": 31, "b": -12000, "c": 5}


@pytest.mark.parametrize("pad", ["", _PAD])  # the pure-Python and libyaml paths
def test_no_base_60_numbers(pad):
    """YAML 1.1 read 1:00 as 60 and 1:30.5 as 90.5 (YAML 1.2 dropped it): strings now."""
    data = _load(pad + "a: 1:00\nb: 1:30.5\nc: 12:34:56\nd: 0x1F\ne: 1_000\nf: .inf\n")
    assert data == {"a": "1:00", "b": "1:30.5", "c": "12:34:56", "d": 31, "e": 1000, "f": math.inf}
    # nor YAML 1.1's octal: 010 was 8 while 08 was a string; both are strings now
    assert _load(pad + "a: 010\nb: 08\nc: 0\nd: -0\ne: 0.5\n") == {
        "a": "010",
        "b": "08",
        "c": 0,
        "d": 0,
        "e": 0.5,
    }
