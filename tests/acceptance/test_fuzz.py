"""Property tests: random configs, random bytes and tampered runs never end in a traceback.

Every example ends either in a valid result or in exactly one line
``error: ...`` with exit status 2 (a :class:`~gcm_pipeline.errors.GcmError`
below the CLI). Configs go through ``gcm validate`` in-process; grasp files
of every format through the reader the candidate stage uses; run
directories through ``gcm show``. Example counts are kept small so the suite
stays fast; hypothesis keeps any failing example in ``.hypothesis/``.
"""

from __future__ import annotations

import io as _io
import json
import os
import shutil
import tempfile
import typing
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import FLAT, assert_one_line_error
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel

from gcm_pipeline.cli import main
from gcm_pipeline.config import Config, load_config
from gcm_pipeline.errors import ConfigError, InputError
from gcm_pipeline.sources.files import acronym, read_grasp_file

#: Examples per test (more with GCM_FUZZ_SCALE=10, e.g., for a longer hunt).
SCALE = float(os.environ.get("GCM_FUZZ_SCALE", "1"))
FUZZ = settings(
    max_examples=int(40 * SCALE),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


def _keys(model: type[BaseModel], out: set[str]) -> set[str]:
    """Every field name of the config's sections (the keys worth mixing in)."""
    for name, field in model.model_fields.items():
        out.add(name)
        stack = [field.annotation]
        while stack:
            ann = stack.pop()
            if isinstance(ann, type) and issubclass(ann, BaseModel) and ann is not model:
                _keys(ann, out)
            else:
                stack.extend(a for a in typing.get_args(ann) if a is not Ellipsis)
    return out


KEYS = sorted(_keys(Config, set()))
scalars = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**70), max_value=2**70)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=20)
    | st.sampled_from(["plane", "cylinder", "file", "mesh", "qhull", "xy", "mink", "nope.npy"])
)
keys = st.sampled_from(KEYS) | st.text(min_size=1, max_size=8)
trees = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(keys, inner, max_size=5),
    max_leaves=25,
)


def _validate(capsys, text: str) -> None:
    """``gcm validate`` on a config text: ok, or one line ``error: ...`` with status 2."""
    with tempfile.TemporaryDirectory(prefix="gcm-fuzz-") as d:
        path = Path(d) / "cfg.yaml"
        path.write_text(text, encoding="utf-8")
        code = main(["validate", str(path)])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if not ln.startswith("WARNING")]
    if code == 0:
        assert out.startswith("# ") and lines == [], (out, err)
    else:
        assert_one_line_error(code, err, warnings=True)


@settings(FUZZ, max_examples=int(25 * SCALE))
@given(st.dictionaries(keys, trees, max_size=6))
def test_random_config_trees(capsys, data):
    _validate(capsys, yaml.safe_dump(data, allow_unicode=True))


FLAT_DATA = yaml.safe_load(FLAT.read_text())


@FUZZ
@given(
    st.lists(
        st.tuples(st.sampled_from(KEYS), st.sampled_from(KEYS), trees, st.booleans()),
        min_size=1,
        max_size=3,
    )
)
def test_mutated_valid_configs(capsys, edits):
    """The example config with sections or keys replaced, added or removed."""
    data = json.loads(json.dumps(FLAT_DATA))
    for section, key, value, nested in edits:
        if nested and isinstance(data.get(section), dict):
            data[section][key] = value
        elif nested:
            data[section] = {key: value}
        else:
            data[section] = value
    _validate(capsys, yaml.safe_dump(data, allow_unicode=True))


@FUZZ
@given(
    st.lists(
        st.tuples(st.integers(0, 2000), st.integers(0, 8), st.text(max_size=6)),
        min_size=1,
        max_size=4,
    )
)
def test_mangled_config_text(edits):
    """Cut and pasted YAML source: a ConfigError (one line) or a valid config."""
    text = FLAT.read_text()
    for at, cut, paste in edits:
        at %= len(text) + 1
        text = text[:at] + paste + text[at + cut :]
    with tempfile.TemporaryDirectory(prefix="gcm-fuzz-") as d:
        path = Path(d) / "cfg.yaml"
        path.write_text(text, encoding="utf-8")
        try:
            cfg = load_config(path)
        except ConfigError as exc:
            assert "\n" not in str(exc).strip()
        else:
            assert isinstance(cfg, Config)


# --------------------------------------------------------------- grasp files


def _poses(n: int) -> np.ndarray:
    t = np.tile(np.eye(4), (n, 1, 1))
    t[:, 0, 3] = np.linspace(0.3, 0.6, n)
    return t


def _valid_bytes(fmt: str) -> bytes:
    buf = _io.BytesIO()
    if fmt == "npy":
        np.save(buf, _poses(6))
    elif fmt == "npz":
        np.savez(buf, transforms=_poses(6), success=np.ones(6), score=np.linspace(0, 1, 6))
    elif fmt == "csv":
        rows = "".join(f"{i},{0.3 + 0.05 * i},0,0.2,0,1,0,0,1,0.{i}\n" for i in range(6))
        return ("id,x,y,z,qw,qx,qy,qz,success,score\n" + rows).encode()
    else:
        h5py = pytest.importorskip("h5py")
        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / "g.h5"
            with h5py.File(path, "w") as f:
                f["grasps/transforms"] = _poses(6)
                f["grasps/qualities/flex/object_in_gripper"] = np.ones(6)
                f["object/file"] = "meshes/mug.obj"
                f["object/scale"] = 1.0
            return path.read_bytes()
    return buf.getvalue()


VALID = {fmt: _valid_bytes(fmt) for fmt in ("npy", "npz", "csv", "acronym")}
mutations = st.lists(
    st.tuples(st.integers(0, 1 << 20), st.integers(0, 255)), min_size=0, max_size=12
)


def _read_or_refuse(fmt: str, data: bytes) -> None:
    with tempfile.TemporaryDirectory(prefix="gcm-fuzz-") as d:
        path = Path(d) / f"g.{ {'acronym': 'h5'}.get(fmt, fmt) }"
        path.write_bytes(data)
        try:
            poses, columns = read_grasp_file(path, format=fmt)
        except InputError as exc:
            msg = str(exc)
            assert str(path) in msg and "\n" not in msg and len(msg) < 2000, msg
            return
    assert poses.ndim == 3 and poses.shape[1:] == (4, 4) and np.isfinite(poses).all()
    rot = poses[:, :3, :3]
    assert np.allclose(rot @ np.swapaxes(rot, 1, 2), np.eye(3), atol=1e-3)
    assert all(len(v) == len(poses) for v in columns.values())


@pytest.mark.parametrize("fmt", sorted(VALID))
@settings(FUZZ, max_examples=int(30 * SCALE))
@given(mutations=mutations, cut=st.integers(0, 1 << 20), tail=st.binary(max_size=16))
def test_damaged_grasp_files(fmt, mutations, cut, tail):
    """Valid files with bytes changed, cut short or extended: read, or refused in one line."""
    data = bytearray(VALID[fmt])
    for at, byte in mutations:
        data[at % len(data)] = byte
    if cut % 3 == 0:
        data = data[: cut % (len(data) + 1)]
    _read_or_refuse(fmt, bytes(data) + tail)


@pytest.mark.parametrize("fmt", sorted(VALID))
@settings(FUZZ, max_examples=int(15 * SCALE))
@given(data=st.binary(max_size=600))
def test_random_bytes_as_grasp_files(fmt, data):
    _read_or_refuse(fmt, data)


def test_an_hdf5_read_that_never_finishes_is_refused_in_one_line(monkeypatch):
    """One byte changed in a valid ACRONYM file (a damaged variable-length string, found
    by the fuzz test above) made the HDF5 library loop forever in the reader: now the read
    is given up after its time limit, refused in one line, and its child process killed."""
    import multiprocessing as mp
    import time

    monkeypatch.setattr(acronym, "_HDF5_SECONDS", 2.0)
    data = bytearray(VALID["acronym"])
    data[7112] = 97  # with h5py's layout of this file: the object/file string's heap entry
    t0 = time.monotonic()
    _read_or_refuse("acronym", bytes(data) + b"\x00")
    assert time.monotonic() - t0 < 30
    assert not mp.active_children()

    # a reader that never returns, whatever the h5py version writes
    monkeypatch.setattr(acronym, "_read_acronym_here", lambda path, n: time.sleep(600))
    with tempfile.TemporaryDirectory(prefix="gcm-fuzz-") as d:
        path = Path(d) / "g.h5"
        path.write_bytes(VALID["acronym"])
        with pytest.raises(InputError, match="did not finish reading it in 2 s; the file"):
            read_grasp_file(path, format="acronym")
    assert not mp.active_children()


# --------------------------------------------------------------- tampered run directories


@settings(FUZZ, max_examples=int(40 * SCALE))
@given(
    name=st.sampled_from(["grasps.csv", "summary.json", "manifold.npz"]),
    mutations=mutations,
    cut=st.integers(0, 1 << 20),
)
def test_tampered_runs_show(capsys, flat_run, name, mutations, cut):
    """``gcm show`` on a run with one file damaged: the table, or one error line."""
    with tempfile.TemporaryDirectory(prefix="gcm-fuzz-") as d:
        copy = Path(d) / "run"
        shutil.copytree(flat_run, copy)
        data = bytearray((copy / name).read_bytes())
        for at, byte in mutations:
            data[at % len(data)] = byte
        if cut % 4 == 0:
            data = data[: cut % (len(data) + 1)]
        (copy / name).write_bytes(bytes(data))
        capsys.readouterr()
        code = main(["show", str(copy)])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    if code == 0:
        assert out.startswith("run ")
    else:
        assert_one_line_error(code, err)
