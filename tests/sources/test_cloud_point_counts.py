"""A cloud file that holds another number of points than its header says is refused.

A cloud cut short (a partial download, a crashed writer) would otherwise be
read as fewer obstacles, and grasps that collide with the missing clutter
judged free. The binary PCD reader already refused it; the ascii PCD and the
PLY readers took whatever rows were there.
"""

from __future__ import annotations

import pytest

from gcm_pipeline.errors import InputError
from gcm_pipeline.sources.clouds import CloudOptions, read_cloud

WHERE = "environment.point_clouds[0]"


def _pcd(points: str, rows: list[str], fields: str = "x y z") -> str:
    k = len(fields.split())
    return (
        f"# .PCD v0.7\nVERSION 0.7\nFIELDS {fields}\nSIZE {' '.join(['4'] * k)}\n"
        f"TYPE {' '.join(['F'] * k)}\nCOUNT {' '.join(['1'] * k)}\nWIDTH 3\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA ascii\n" + "\n".join(rows) + "\n"
    )


def _read(path):
    with pytest.raises(InputError) as err:
        read_cloud(CloudOptions(path, where=WHERE))
    msg = str(err.value)
    assert "\n" not in msg and WHERE in msg and str(path) in msg, msg
    return msg


@pytest.mark.parametrize(
    ("points", "rows", "fragment"),
    [
        ("10", ["0.5 0 0.3"], "holds 1 point, its header says POINTS 10"),
        ("1", ["0.5 0 0.3", "0.5 0.1 0.3"], "holds more than its POINTS 1"),
        ("-5", ["0.5 0 0.3"], "POINTS -5"),
    ],
)
def test_an_ascii_pcd_of_another_size_than_its_header(tmp_path, points, rows, fragment):
    path = tmp_path / "c.pcd"
    path.write_text(_pcd(points, rows))
    assert fragment in _read(path)


def test_an_ascii_pcd_row_narrower_than_its_fields(tmp_path):
    path = tmp_path / "c.pcd"
    path.write_text(_pcd("2", ["0.5 0", "0.5 0.1"]))
    assert "rows of 2 values; FIELDS and COUNT give 3" in _read(path)


def test_an_ascii_pcd_as_its_header_says_is_read(tmp_path):
    path = tmp_path / "c.pcd"
    path.write_text(_pcd("2", ["0.5 0 0.3", "nan nan nan"]))
    cloud = read_cloud(CloudOptions(path, where=WHERE, voxel_size=0.01))
    assert len(cloud.points) == 1  # the NaN point is counted and dropped, as before


def test_an_ascii_ply_cut_short(tmp_path):
    path = tmp_path / "c.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 1000\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n0.5 0 0.3\n0.5 0.1 0.3\n"
    )
    assert "holds 2 points, its header says element vertex 1000" in _read(path)
