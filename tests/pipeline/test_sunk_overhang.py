"""The sunk-object warning measures the part of the object over the table.

An object across the table's edge, tilted, touches the top over the table and
dips lower beside it (in the air): only the part over the table is in the
table, and only that part decides the warning and how far to raise it.
"""

from __future__ import annotations

import math

import pytest
from helpers import ROOT

BOX = ROOT / "configs" / "box.yaml"  # the 2 x 2 m table's top at z = 0, its edge at x = 1


def _tilted_across_the_edge(into: float) -> list[str]:
    """A 30 x 6 x 6 cm box centred over the edge x = 1, pitched 20 deg (its +x end down).

    Over the table its lowest point is on the edge, ``into`` [m] under the top;
    beside the table its lowest corner is 48 mm lower than that.
    """
    t = math.radians(20.0)
    zc = 0.03 / math.cos(t) - into
    return [
        "object.dims.size=[0.3,0.06,0.06]",
        f"object.pose.xyz=[1.0,0.0,{zc!r}]",
        "object.pose.rpy_deg=[0,20,0]",
    ]


@pytest.mark.parametrize(("into", "warned_mm"), [(0.0005, None), (0.004, 4.0)])
def test_an_object_over_the_edge_is_measured_over_the_table(cli, into, warned_mm):
    args = [a for o in _tilted_across_the_edge(into) for a in ("--set", o)]
    code, _, err = cli("validate", BOX, *args)
    assert code == 0, err
    sunk = [line for line in err.splitlines() if "the table" in line and "raise its" in line]
    if warned_mm is None:
        assert sunk == []
    else:
        assert len(sunk) == 1
        assert f"reaches {warned_mm:.1f} mm into the table" in sunk[0]
        assert f"raise its pose's z by {warned_mm / 1e3:.4g}" in sunk[0]
