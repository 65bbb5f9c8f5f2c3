"""The arm's joints as a spec sets them: locked joints, joint ranges, home.

Used when a :class:`~gcm_pipeline.robot.model.Robot` is built: the spec's locked
joints (checked against the full model) and the mimic joints that follow them,
each joint's range (the model's, intersected with the spec's ``joint_limits``,
less ``limit_margin`` on revolute joints; an "unlimited" +-1e308 or an empty
range refused in one line), and the home configuration (the spec's, else the
middle of every range).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pinocchio as pin

from gcm_pipeline.errors import RobotSpecError, choice_error
from gcm_pipeline.robot.urdf import Mimic, PreparedUrdf

if TYPE_CHECKING:
    from gcm_pipeline.robot.model import RobotSpec

__all__ = [
    "MAX_JOINT_BOUND",
    "home_configuration",
    "joint_ranges",
    "locked_joints",
    "mimic_locks",
]

#: Largest joint bound accepted [rad or m]; a URDF's "unlimited" +-1e308 is refused.
MAX_JOINT_BOUND = 1000.0


def mimic_locks(spec: RobotSpec, mimic: Mapping[str, Mimic]) -> dict[str, float]:
    """The spec's locked joints with every mimic joint of a locked joint added.

    A joint that mimics a locked joint is locked at ``multiplier * value + offset``
    (also one whose leader mimics a locked joint in turn), as the real mechanism holds
    it: locking a gripper's driven joint at an opening puts its linkage there. A mimic
    joint the spec locks at another value is refused in one line.
    """
    locked = spec.locked_joints
    values = dict(locked)
    pending = {j: m for j, m in mimic.items() if m.leader in values or m.leader in mimic}
    while pending:
        ready = [j for j, m in pending.items() if m.leader not in pending]
        if not ready:  # a cycle of mimic joints: none of them follows a locked joint
            break
        for joint in ready:
            m = pending.pop(joint)
            if m.leader not in values:
                continue
            follow = m.multiplier * values[m.leader] + m.offset
            given = locked.get(joint)
            if given is not None and abs(given - follow) > 1e-9:
                raise RobotSpecError(
                    f"robot {spec.name!r}: locked_joints.{joint} = {given:g}, but {joint!r} "
                    f"mimics {m.leader!r} in the URDF ({m.multiplier:g} * {values[m.leader]:g}"
                    f" + {m.offset:g} = {follow:g}): drop it (it follows {m.leader!r})"
                )
            values[joint] = follow
    return values


def locked_joints(
    spec: RobotSpec, full: Any, mimic: Mapping[str, Mimic] | None = None
) -> tuple[np.ndarray, list[int], dict[str, float]]:
    """The full model's configuration with the locked joints set, their ids and values.

    The locked joints are the spec's and the mimic joints that follow them
    (:func:`mimic_locks`). A mimic joint's value is its leader's business: its own
    URDF range, often written for the other sign of the multiplier, is not checked.
    """
    mimic = mimic or {}
    # the spec's own values first: a leader outside its range is named as such
    for jname, value in spec.locked_joints.items():
        _lock_index(spec, full, jname, value, mimic)
    locked_q = pin.neutral(full)
    locked_ids = []
    for jname, value in mimic_locks(spec, mimic).items():
        iq = _lock_index(spec, full, jname, value, mimic)
        if iq is None:
            continue
        locked_q[iq] = value
        locked_ids.append(full.getJointId(jname))
    return (
        locked_q,
        locked_ids,
        {full.names[j]: float(locked_q[full.joints[j].idx_q]) for j in locked_ids},
    )


def _lock_index(
    spec: RobotSpec, full: Any, jname: str, value: float, mimic: Mapping[str, Mimic]
) -> int | None:
    """The configuration index of a joint to lock, checked; None for a fixed mimic joint."""
    if not full.existJointName(jname):
        if jname in mimic and jname not in spec.locked_joints:
            return None  # a fixed joint with a <mimic>: nothing to lock
        raise choice_error(
            RobotSpecError,
            "joint",
            jname,
            [full.names[i] for i in range(1, full.njoints)],
            key="locked_joints",
            prefix=f"robot {spec.name!r}: locked_joints: ",
        )
    jid = full.getJointId(jname)
    if full.joints[jid].nq != 1:
        raise RobotSpecError(f"robot {spec.name!r}: cannot lock multi-DoF joint {jname!r}")
    iq = int(full.joints[jid].idx_q)
    lo, hi = full.lowerPositionLimit[iq], full.upperPositionLimit[iq]
    if jname not in mimic and not lo - 1e-9 <= value <= hi + 1e-9:
        raise RobotSpecError(
            f"robot {spec.name!r}: locked_joints.{jname} = {value:g} is outside the "
            f"joint's range [{lo:g}, {hi:g}]"
        )
    return iq


def joint_ranges(
    spec: RobotSpec, model: Any, prepared: PreparedUrdf, continuous: Mapping[str, Any], urdf: Path
) -> tuple[np.ndarray, np.ndarray]:
    """Joint ranges (nq,) [rad or m]: the model's, intersected with the spec's, less the margin."""
    joint_names = tuple(model.names[i] for i in range(1, model.njoints))
    lower = np.array(model.lowerPositionLimit, dtype=float)
    upper = np.array(model.upperPositionLimit, dtype=float)
    for jname, (lo, hi) in spec.joint_limits.items():
        if jname not in joint_names:
            raise choice_error(
                RobotSpecError,
                "joint",
                jname,
                joint_names,
                key="joint_limits",
                prefix=f"robot {spec.name!r}: joint_limits: ",
            )
        i = joint_names.index(jname)
        lower[i], upper[i] = max(lower[i], lo), min(upper[i], hi)
    for i, jname in enumerate(joint_names):
        lo, hi = float(lower[i]), float(upper[i])
        if not (abs(lo) <= MAX_JOINT_BOUND and abs(hi) <= MAX_JOINT_BOUND):
            raise RobotSpecError(
                f"robot {spec.name!r}: joint {jname!r} has the range [{lo:g}, {hi:g}] in "
                f"{str(urdf)!r}, beyond +-{MAX_JOINT_BOUND:g} (rad or m); give its real "
                f"range in the spec: joint_limits: {{{jname}: [lower, upper]}}"
            )
    # the margin is in radians: revolute joints only (a prismatic range is in metres),
    # and not a continuous joint's stated range of two turns (no limit to keep off)
    revolute = np.zeros(model.nq, dtype=bool)
    for j in range(1, model.njoints):
        joint = model.joints[j]
        limited = model.names[j] not in continuous or (model.names[j] in spec.joint_limits)
        if joint.nq == 1 and limited and not joint.shortname()[10:].startswith("P"):
            revolute[joint.idx_q] = True
    lower += np.where(revolute, spec.limit_margin, 0.0)
    upper -= np.where(revolute, spec.limit_margin, 0.0)
    for i, jname in enumerate(joint_names):
        if not lower[i] < upper[i]:
            why = (
                f" (the URDF gives it no lower/upper; give joint_limits: {{{jname}: "
                "[lower, upper]})"
                if jname in prepared.unbounded
                else ""
            )
            raise RobotSpecError(
                f"robot {spec.name!r}: joint {jname!r} has an empty range "
                f"[{lower[i]:g}, {upper[i]:g}] after joint_limits and limit_margin "
                f"({spec.limit_margin:g}){why}"
            )
    return lower, upper


def home_configuration(
    spec: RobotSpec, joint_names: tuple[str, ...], lower: np.ndarray, upper: np.ndarray
) -> np.ndarray:
    """The home configuration (nq,) [rad]: the spec's, else the middle of every range."""
    if isinstance(spec.home, tuple):
        if len(spec.home) != len(joint_names):
            raise RobotSpecError(
                f"robot {spec.name!r}: home has {len(spec.home)} values, "
                f"expected {len(joint_names)}"
            )
        home = np.array(spec.home, dtype=float)
    else:
        home = 0.5 * (lower + upper)
        for jname, value in spec.home.items():
            if jname not in joint_names:
                raise choice_error(
                    RobotSpecError,
                    "joint",
                    jname,
                    joint_names,
                    key="home",
                    prefix=f"robot {spec.name!r}: home: ",
                )
            home[joint_names.index(jname)] = value
    if np.any(home < lower) or np.any(home > upper):
        raise RobotSpecError(
            f"robot {spec.name!r}: home {home.tolist()} is outside the joint limits"
        )
    return home
