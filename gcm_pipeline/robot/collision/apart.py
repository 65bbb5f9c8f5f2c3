"""Pairs no configuration brings together: a link whose height over a world box never changes.

A joint that turns about an axis parallel to a direction ``n``, or slides
perpendicular to it, leaves the component along ``n`` of every point it moves
unchanged (a rotation about an axis parallel to ``n`` maps ``n`` to itself);
it also keeps the later joints' axes parallel to ``n``, or perpendicular to
it, if they were at home. So when every joint from the base to a link is such
a joint for the normal ``n`` of a face of a world box (the table under a UR's
shoulder, which turns about the vertical), the link's height over that face's
plane is the same in every configuration. If every point of the link's
geometry (its hull's vertices; a primitive's local bounding box, which
contains it) lies beyond that plane by more than a margin at home, the pair
is free in every configuration: the broad phase's level 3 would call it free
each time (:mod:`~gcm_pipeline.robot.collision.broadphase`), so the checker
drops it once, at construction, with the same answers.
"""

from __future__ import annotations

from typing import Any

import coal
import numpy as np
import pinocchio as pin

from gcm_pipeline.robot.collision.pairs import Pair
from gcm_pipeline.robot.collision.spheres import geometry_mesh
from gcm_pipeline.robot.model import Robot

__all__ = ["AXIS_TOLERANCE", "pairs_apart"]

#: A joint axis is parallel (or perpendicular) to a face normal when the
#: cross (or dot) product of the unit vectors is at most this: over a 2 m reach
#: the heights then change by at most about 1e-11 m, far below any margin.
AXIS_TOLERANCE = 1e-12


def pairs_apart(robot: Robot, gm: Any, pairs: list[Pair], margin: float) -> set[int]:
    """Indices of the world pairs free in every configuration (see the module doc).

    Args:
        robot: The robot (its model and home configuration).
        gm: The checker's geometry model (robot and world geometries).
        pairs: The checked pairs.
        margin: Every point of the link must lie farther than this beyond the
            face's plane [m].

    Returns:
        Indices into ``pairs`` of pairs (a robot geometry against a box fixed
        to the world) that no configuration brings within ``margin``.
    """
    model = robot.model
    data = model.createData()
    home = np.asarray(robot.home, dtype=float)
    pin.computeJointJacobians(model, data, home)
    gd = pin.GeometryData(gm)
    pin.updateGeometryPlacements(model, data, gm, gd, home)
    motions = _joint_motions(model, data)
    apart = set()
    for k, p in enumerate(pairs):
        link, shape = gm.geometryObjects[p.a], gm.geometryObjects[p.b]
        if p.kind == "self" or shape.parentJoint != 0 or link.parentJoint == 0:
            continue
        if not isinstance(shape.geometry, coal.Box):
            continue
        box = gd.oMg[p.b]
        rot = np.asarray(box.rotation)
        # the faces whose heights no joint changes (most links: none, and no mesh is read)
        axes = [
            a for a in range(3) if _heights_fixed(model, motions, int(link.parentJoint), rot[:, a])
        ]
        if not axes:
            continue
        half = np.asarray(shape.geometry.halfSide, dtype=float)
        points, _ = geometry_mesh(link.geometry)
        placed = gd.oMg[p.a]
        world = points @ np.asarray(placed.rotation).T + np.asarray(placed.translation)
        local = (world - np.asarray(box.translation)) @ rot
        for axis in axes:
            x = local[:, axis]
            if np.all(x > half[axis] + margin) or np.all(x < -half[axis] - margin):
                apart.add(k)
                break
    return apart


def _joint_motions(model: Any, data: Any) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """Per joint, the linear and angular parts of its motion at home (None: not one DoF).

    ``data`` holds the joint Jacobians at home (``computeJointJacobians``).
    """
    out: list[tuple[np.ndarray, np.ndarray] | None] = [None]
    for j in range(1, model.njoints):
        joint = model.joints[j]
        if joint.nv != 1:
            out.append(None)
            continue
        col = pin.getJointJacobian(model, data, j, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)[
            :, joint.idx_v
        ]
        out.append((col[:3].copy(), col[3:].copy()))
    return out


def _heights_fixed(
    model: Any, motions: list[tuple[np.ndarray, np.ndarray] | None], joint: int, normal: np.ndarray
) -> bool:
    """Whether every joint from the base to ``joint`` keeps heights along ``normal``.

    Each must move one coordinate (``nv == 1``) and, at home, turn about an
    axis parallel to ``normal`` or slide perpendicular to it.
    """
    while joint > 0:
        motion = motions[joint]
        if motion is None:
            return False
        linear, angular = motion
        if np.linalg.norm(np.cross(angular, normal)) > AXIS_TOLERANCE:
            return False
        if abs(float(linear @ normal)) > AXIS_TOLERANCE:
            return False
        joint = int(model.parents[joint])
    return True
