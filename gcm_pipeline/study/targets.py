"""What a pose sweep moves: a pose of the config, as ``--set KEY=VALUE`` overrides.

A configured object and the robot base move by their pose (``object.pose``,
``robot.base_pose``): ``x, y, z`` [m] set its position in the world and
``yaw_deg`` [deg] the yaw of its roll-pitch-yaw (:class:`PoseTarget`). An
object its grasp file names (no ``object`` section; see
:func:`~gcm_pipeline.pipeline.place_file_object`) moves by
``candidates.placement`` (:class:`PlacementTarget`): ``x, y`` are the centre
of its footprint on the table and ``yaw_deg`` its turn about the vertical;
its stable pose fixes its height, so it has no ``z`` to sweep.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import yaml

__all__ = ["PlacementTarget", "PoseTarget", "format_value"]


def format_value(value: Any) -> str:
    """A value as flow YAML for a ``--set KEY=VALUE`` override (floats round-trip).

    PyYAML writes floats with :func:`repr` and a ``.0`` before an exponent, so
    ``yaml.safe_load`` reads back the same float (``1e-05`` alone would be a string).
    """
    if isinstance(value, list) and all(type(v) in (float, int) for v in value):
        return "[" + ", ".join(_yaml_number(v) for v in value) + "]"  # a pose: no YAML dump
    text = yaml.safe_dump(value, default_flow_style=True, width=math.inf, sort_keys=False)
    text = text.strip()
    if text.endswith("\n...") or text.endswith("..."):
        text = text[: text.rfind("...")].strip()
    return text


def _yaml_number(v: float) -> str:
    """A float or int as PyYAML's safe representer writes it (its rules, 30x faster)."""
    if type(v) is int:
        return str(v)
    if math.isnan(v):
        return ".nan"
    if math.isinf(v):
        return ".inf" if v > 0 else "-.inf"
    text = repr(v).lower()
    return text.replace("e", ".0e", 1) if "." not in text and "e" in text else text


class PoseTarget:
    """A pose the sweep moves: its config key and the base config's value.

    Attributes:
        key: The pose's config key (``object.pose``, ``robot.base_pose``).
        xyz: The base config's position [m] (the value of an axis not swept).
    """

    def __init__(self, key: str, pose: dict[str, Any] | None) -> None:
        pose = pose or {}
        self.key = key
        self.xyz = [float(v) for v in pose.get("xyz", (0.0, 0.0, 0.0))]
        if pose.get("rpy_deg") is not None:
            self.rot_key, rot = "rpy_deg", pose["rpy_deg"]
        elif pose.get("rpy") is not None:
            self.rot_key, rot = "rpy", pose["rpy"]
        else:
            self.rot_key, rot = "rpy_deg", (0.0, 0.0, 0.0)
        self.rot = [float(v) for v in rot]

    def overrides(self, values: dict[str, float]) -> list[str]:
        """The overrides that set the swept ``values`` (axis -> value)."""
        out = []
        if any(a in values for a in ("x", "y", "z")):
            xyz = [values.get(a, self.xyz[i]) for i, a in enumerate(("x", "y", "z"))]
            out.append(f"{self.key}.xyz={format_value(xyz)}")
        if "yaw_deg" in values:
            yaw = values["yaw_deg"]
            if self.rot_key == "rpy":
                yaw = math.radians(yaw)
            rot = [self.rot[0], self.rot[1], yaw]
            out.append(f"{self.key}.{self.rot_key}={format_value(rot)}")
        return out


class PlacementTarget(PoseTarget):
    """An object its grasp file names, moved by ``candidates.placement``.

    Its position is the centre of its footprint: ``xy`` on the table top at
    height ``table_z`` (which its stable pose fixes: ``z`` is not swept).
    """

    def __init__(self, xy: Sequence[float], table_z: float) -> None:
        self.key = "candidates.placement"
        self.xyz = [float(xy[0]), float(xy[1]), float(table_z)]

    def overrides(self, values: dict[str, float]) -> list[str]:
        """The overrides of ``candidates.placement`` for the swept ``x, y, yaw_deg``."""
        out = []
        if "x" in values or "y" in values:
            xy = [values.get("x", self.xyz[0]), values.get("y", self.xyz[1])]
            out.append(f"{self.key}.xy={format_value(xy)}")
        if "yaw_deg" in values:
            out.append(f"{self.key}.yaw_deg={format_value(values['yaw_deg'])}")
        return out
