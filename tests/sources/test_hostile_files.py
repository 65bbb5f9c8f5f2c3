"""Broken and hostile grasp files end in one line naming the file (an ``InputError``).

Every format the sources read (truncated, corrupt, lying headers, oversized,
wrong encodings), and ``gcm validate`` reading the candidates as a run does.
"""

from __future__ import annotations

import io as _io
import re
import zipfile
from pathlib import Path

import numpy as np
import pytest
from helpers import ROOT, assert_one_line_error

from gcm_pipeline.errors import InputError
from gcm_pipeline.sources.files import read_grasp_file
from gcm_pipeline.sources.files.acronym import read_acronym_object
from gcm_pipeline.sources.files.common import RESERVED_COLUMNS
from gcm_pipeline.table import COLUMNS


def _poses(n: int) -> np.ndarray:
    t = np.tile(np.eye(4), (n, 1, 1))
    t[:, 0, 3] = 0.4 + 0.01 * np.arange(n)
    t[:, 1, 3] = 0.05 * (np.arange(n) % 3)
    t[:, 2, 3] = 0.3
    t[:, :3, :3] = np.diag([1.0, -1.0, -1.0])
    return t


def _npy_bytes(arr: np.ndarray) -> bytes:
    buf = _io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


def _npz_bytes(**arrays) -> bytes:
    buf = _io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _lying_header(shape) -> bytes:
    hdr = np.lib.format.header_data_from_array_1_0(np.zeros((1, 4, 4)))
    hdr["shape"] = shape
    buf = _io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, hdr)
    return buf.getvalue() + b"\0" * 1024


def _zip(members: dict[str, bytes]) -> bytes:
    buf = _io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for name, data in members.items():
            z.writestr(name, data)
    return buf.getvalue()


def _crc_broken() -> bytes:
    raw = bytearray(_npz_bytes(transforms=_poses(5)))
    raw[200:230] = b"\xff" * 30  # inside the member's data
    return bytes(raw)


BROKEN_FILES = {
    "npy header claims 10^10 poses": ("g.npy", _lying_header((10**10, 4, 4)), "truncated"),
    "npy truncated": ("g.npy", _npy_bytes(_poses(50))[:300], "truncated"),
    "npy of pickled objects": ("g.npy", None, "Python objects"),
    "npy that is an npz": ("g.npy", _npz_bytes(transforms=_poses(3)), "use format: npz"),
    "npy wrong shape": ("g.npy", _npy_bytes(np.zeros((3, 3, 4))), "shape (N, 4, 4)"),
    "npz truncated": ("g.npz", _npz_bytes(transforms=_poses(5))[:200], "not a readable .npz"),
    "npz bad CRC": ("g.npz", _crc_broken(), "Bad CRC-32"),
    "npz member not .npy": ("g.npz", _zip({"notes.txt": b"hello"}), "is not a .npy array"),
    "npz member garbage": ("g.npz", _zip({"transforms.npy": b"hello"}), "not a .npy array"),
    "npz lying member header": (
        "g.npz",
        _zip({"transforms.npy": _lying_header((10**10, 4, 4))}),
        "truncated",
    ),
    "npz no poses": ("g.npz", _npz_bytes(a=np.zeros(3), b=np.zeros(3)), "'transforms'"),
    "csv duplicate columns": ("g.csv", b"x,y,z,qw,qx,qy,qz,x\n0,0,0,1,0,0,0,1\n", "twice"),
    "csv reserved column": ("g.csv", b"x,y,z,qw,qx,qy,qz,rank\n0,0,0,1,0,0,0,1\n", "rename it"),
    "csv grasp-table column": (
        "g.csv",
        b"x,y,z,qw,qx,qy,qz,patch\n0,0,0,1,0,0,0,1\n",
        "has the name of a grasp-table column; rename it (e.g. input_patch)",
    ),
    "csv not utf-8": ("g.csv", b"x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n# caf\xe9\n", "not UTF-8"),
    "csv huge field": (
        "g.csv",
        b"x,y,z,qw,qx,qy,qz\n" + b"1" * 200_000 + b",0,0,1,0,0,0\n",
        "field larger",
    ),
    "csv not a number": ("g.csv", b"x,y,z,qw,qx,qy,qz\n0,a,0,1,0,0,0\n", ":2: column 'y'"),
    "csv quaternion norm": ("g.csv", b"x,y,z,qw,qx,qy,qz\n0,0,0,5,0,0,0\n", "norm 5"),
}


@pytest.mark.parametrize("case", sorted(BROKEN_FILES))
def test_broken_grasp_files_are_one_line_errors(tmp_path, case):
    name, data, fragment = BROKEN_FILES[case]
    path = tmp_path / name
    if data is None:
        np.save(path, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    else:
        path.write_bytes(data)
    with pytest.raises(InputError) as info:
        read_grasp_file(path)
    msg = str(info.value)
    assert str(path) in msg and fragment in msg, msg
    assert "\n" not in msg and len(msg) < 600


@pytest.mark.parametrize("name", sorted(COLUMNS))
def test_every_column_a_run_adds_is_reserved(tmp_path, name):
    # a file's column of that name would be overwritten by the run's (or pass for it)
    header = "x,y,z,qw,qx,qy,qz," + name.upper()  # names are matched in lower case
    (tmp_path / "g.csv").write_text(header + "\n0,0,0,1,0,0,0,1\n")
    with pytest.raises(InputError, match=f"rename it \\(e.g. input_{name}\\)"):
        read_grasp_file(tmp_path / "g.csv")
    assert name in RESERVED_COLUMNS


def test_file_sizes_are_checked_against_max_count_before_reading(tmp_path):
    np.save(tmp_path / "g.npy", _poses(30))
    with pytest.raises(InputError, match="holds 30 grasps, more than candidates.max_count"):
        read_grasp_file(tmp_path / "g.npy", max_count=20)
    np.savez(tmp_path / "g.npz", transforms=_poses(30))
    with pytest.raises(InputError, match="more than"):
        read_grasp_file(tmp_path / "g.npz", max_count=20)
    rows = "".join(f"0.4,{0.01 * i},0.3,0,1,0,0\n" for i in range(30))
    (tmp_path / "g.csv").write_text("x,y,z,qw,qx,qy,qz\n" + rows)
    with pytest.raises(InputError, match="more than candidates.max_count"):
        read_grasp_file(tmp_path / "g.csv", max_count=20)
    assert len(read_grasp_file(tmp_path / "g.csv", max_count=30)[0]) == 30


def test_csv_as_spreadsheets_write_it(tmp_path):
    """A UTF-8 byte order mark, CRLF line ends and blank lines are fine."""
    text = "X,Y,Z,QW,QX,QY,QZ\r\n0.5,0,0.2,0,1,0,0\r\n\r\n0.5,0.1,0.2,0,1,0,0\r\n\r\n\r\n"
    (tmp_path / "g.csv").write_bytes(b"\xef\xbb\xbf" + text.encode())
    poses, columns = read_grasp_file(tmp_path / "g.csv")
    assert poses.shape == (2, 4, 4)
    assert columns["source_id"].tolist() == [0, 1]


# ---------------------------------------------------------------- HDF5 (ACRONYM)


def _h5(tmp_path, build) -> Path:
    h5py = pytest.importorskip("h5py")
    path = tmp_path / "g.h5"
    with h5py.File(path, "w") as f:
        f["grasps/transforms"] = _poses(4)
        f["grasps/qualities/flex/object_in_gripper"] = np.ones(4)
        build(f, h5py)
    return path


def _h5_del(f, key):
    del f[key]


H5_CASES = {
    "non-numeric object/scale": (
        lambda f, h: f.update({"object/file": "mug.obj", "object/scale": "big"}),
        "object/scale must be a number",
    ),
    "non-text object/file": (
        lambda f, h: f.update({"object/file": np.arange(3)}),
        "object/file must be a text",
    ),
    "dangling soft link": (
        lambda f, h: f.update({"object/file": h.SoftLink("/nowhere")}),
        "corrupt or unreadable HDF5",
    ),
    "dangling external link": (
        lambda f, h: f.update({"object/scale": h.ExternalLink("missing.h5", "/x")}),
        "corrupt or unreadable HDF5",
    ),
    "transforms of strings": (
        lambda f, h: (_h5_del(f, "grasps/transforms"), f.update({"grasps/transforms": [b"a"]})),
        "must hold numbers",
    ),
    "transforms is a group": (
        lambda f, h: (_h5_del(f, "grasps/transforms"), f.create_group("grasps/transforms")),
        "not a dataset",
    ),
    "success of another length": (
        lambda f, h: (
            _h5_del(f, "grasps/qualities/flex/object_in_gripper"),
            f.update({"grasps/qualities/flex/object_in_gripper": np.ones(7)}),
        ),
        "has 7 values, expected 4",
    ),
}


@pytest.mark.parametrize("case", sorted(H5_CASES))
def test_broken_acronym_files(tmp_path, case):
    build, fragment = H5_CASES[case]
    path = _h5(tmp_path, build)
    with pytest.raises(InputError, match=fragment):
        read_grasp_file(path)


def test_corrupted_hdf5_bytes(tmp_path):
    path = _h5(tmp_path, lambda f, h: None)
    raw = bytearray(path.read_bytes())
    raw[600:1400] = b"\x00" * 800
    path.write_bytes(bytes(raw))
    with pytest.raises(InputError, match="HDF5"):
        read_grasp_file(path)


def test_hdf5_library_errors_name_the_file_and_the_place(tmp_path):
    # the grasps are read in a child process, the object's name and scale again in
    # this one (objects from the grasp file): both refuse with the same line
    path = _h5(tmp_path, lambda f, h: f.update({"object/file": h.SoftLink("/nowhere")}))
    line = rf"^{re.escape(str(path))}: corrupt or unreadable HDF5 file \(at object\): \S"
    with pytest.raises(InputError, match=line):
        read_grasp_file(path)
    with pytest.raises(InputError, match=line):
        read_acronym_object(path)


# ---------------------------------------------------------- through gcm validate


def test_validate_reads_the_grasp_file_and_refuses_nul_characters(cli, tmp_path):
    """gcm validate reads the candidates as the run does: a bad grasp file fails there.

    A NUL in a CSV cell was dropped by NumPy's strings (``0`` + NUL read as 0)."""
    cfg = ROOT / "configs" / "from_file.yaml"
    code, out, _ = cli("validate", cfg)
    assert code == 0 and "mug_grasps.npy: 24 grasps" in out.splitlines()[1]
    header = "x,y,z,qw,qx,qy,qz\n"
    rows = "0.5,0,0.1,1,0,0,0\n0.5,0.1,0.1,1,0,0,0\n0.5,0\0,0.1,1,0,0,0\n"
    bad = tmp_path / "nul.csv"
    bad.write_text(header + rows)
    sets = [f"candidates.path={bad}", "candidates.format=csv"]
    code, _, err = cli("validate", cfg, *(a for s in sets for a in ("--set", s)))
    assert_one_line_error(code, err, f"{bad}:4: NUL character in a CSV file")
    broken = tmp_path / "broken.npy"
    broken.write_bytes(b"\x93NUMPY this is not a grasp file")
    code, _, err = cli("validate", cfg, "--set", f"candidates.path={broken}")
    assert_one_line_error(code, err, str(broken))


def test_a_nan_success_label_is_refused_not_read_as_a_failure(tmp_path):
    from gcm_pipeline.sources.files import read_grasps

    success = [1.0, float("nan"), 0.0]
    np.savez(tmp_path / "g.npz", transforms=_poses(3), success=success)
    with pytest.raises(InputError, match=r"array 'success': grasp 1 \(0-based\): success label"):
        read_grasps(tmp_path / "g.npz", "npz", success_only=False)
    pos = _poses(3)[:, :3, 3]
    rows = [f"{x},{y},{z},0,1,0,0,{s}" for (x, y, z), s in zip(pos, success, strict=True)]
    (tmp_path / "g.csv").write_text("x,y,z,qw,qx,qy,qz,success\n" + "\n".join(rows) + "\n")
    with pytest.raises(InputError, match=r"g\.csv:3: column 'success': success label is nan"):
        read_grasps(tmp_path / "g.csv", "csv")
    grasps = "\n".join(f"  - {p.tolist()}" for p in _poses(3))
    (tmp_path / "g.yaml").write_text(
        f"grasps:\n transforms:\n{grasps}\n object_in_gripper: [1, .nan, 0]\n"
    )
    with pytest.raises(InputError, match=r"grasps.object_in_gripper: grasp 1 \(0-based\)"):
        read_grasps(tmp_path / "g.yaml", "graspgen")
