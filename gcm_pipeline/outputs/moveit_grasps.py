"""A run's reachable grasps as ``moveit_msgs/Grasp`` and ``JointTrajectory`` mappings.

Plain mappings with the ROS 2 messages' field names, in the messages'
order (``header.stamp.{sec, nanosec}``): the MoveIt YAML export dumps them,
the MCAP export serialises them (:mod:`gcm_pipeline.outputs.export_mcap`).

``moveit_msgs/Grasp`` fields (from the message definition in moveit_msgs):
``id``; ``pre_grasp_posture`` / ``grasp_posture`` (``trajectory_msgs/
JointTrajectory`` of the hand's finger joints); ``grasp_pose``
(``geometry_msgs/PoseStamped``); ``grasp_quality``; ``pre_grasp_approach``,
``post_grasp_retreat``, ``post_place_retreat`` (``GripperTranslation``:
``direction`` as a ``Vector3Stamped``, ``desired_distance``,
``min_distance``); ``max_contact_force``; ``allowed_touch_objects``.

The arm's trajectory of a grasp (:func:`arm_trajectory`) is the checked
joint solution approach -> grasp -> retreat: ``q_pregrasp`` (end of the
approach, 0 s), ``q`` (the grasp, 1 s), ``q_retreat`` (end of the retreat,
2 s; without a ``retreat`` section the retreat is the approach reversed and
ends at ``q_pregrasp``). The times are nominal (one second per move), not a
time parameterisation; a missing configuration (no approach) is left out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.table import GraspTable

__all__ = ["MoveItOptions", "arm_trajectory", "grasp_messages", "header", "stamp"]

#: Nominal time from the start of an arm trajectory's points [s]: pre-grasp, grasp, retreat.
TRAJECTORY_TIMES = (0.0, 1.0, 2.0)


@dataclass(frozen=True, eq=False)
class MoveItOptions:
    """What a MoveIt export takes from the run's config and robot spec.

    Attributes:
        root_frame: The robot's root frame (``header.frame_id`` of the poses).
        grasp_frame: The spec's grasp frame.
        locked_joints: The spec's locked joints and their values [rad or m].
        base_pose: The robot's base in the world (4, 4) [m].
        metric: The run's ranking metric (``grasp_quality``).
        approach_distance: The checked approach distance [m] (0: none).
        retreat_direction: The retreat's direction (None: the approach reversed).
        retreat_frame: ``world`` or ``grasp``: the frame of ``retreat_direction``.
        retreat_distance: The retreat's distance [m].
        finger_joints: The hand's finger joints among ``locked_joints`` (the
            postures' joints; none: empty postures).
        hand_frame: The hand's base link (the postures' frame; None: the grasp frame).
        joint_names: The arm's joints in configuration order (the columns of
            ``configurations.npz``; the arm trajectories' ``joint_names``).
    """

    root_frame: str
    grasp_frame: str
    locked_joints: Mapping[str, float]
    base_pose: np.ndarray
    metric: str
    approach_distance: float = 0.0
    retreat_direction: tuple[float, float, float] | None = None
    retreat_frame: str = "world"
    retreat_distance: float = 0.0
    finger_joints: tuple[str, ...] = ()
    hand_frame: str | None = None
    joint_names: tuple[str, ...] = ()


def stamp(ns: int = 0) -> dict[str, int]:
    """A ``builtin_interfaces/Time`` (or ``Duration``) of ``ns`` nanoseconds."""
    return {"sec": int(ns // 1_000_000_000), "nanosec": int(ns % 1_000_000_000)}


def header(frame: str, ns: int = 0) -> dict[str, Any]:
    """A ``std_msgs/Header`` in ``frame`` stamped ``ns`` nanoseconds."""
    return {"stamp": stamp(ns), "frame_id": frame}


def _seconds(t: float) -> dict[str, int]:
    sec = int(math.floor(t))
    return {"sec": sec, "nanosec": int(round((t - sec) * 1e9))}


def _translation(
    frame: str, vector: np.ndarray, distance: float, min_distance: float, ns: int
) -> dict:
    x, y, z = (float(v) for v in vector)
    return {
        "direction": {"header": header(frame, ns), "vector": {"x": x, "y": y, "z": z}},
        "desired_distance": float(distance),
        "min_distance": float(min_distance),
    }


def _point(positions: Any, t: float) -> dict[str, Any]:
    return {
        "positions": np.asarray(positions, dtype=float).tolist(),
        "velocities": [],
        "accelerations": [],
        "effort": [],
        "time_from_start": _seconds(t),
    }


def _posture(frame: str, joints: list[str], positions: list[float], t: float, ns: int) -> dict:
    points = [_point(positions, t)] if joints else []
    return {"header": header(frame, ns), "joint_names": list(joints), "points": points}


def _retreat(options: MoveItOptions) -> tuple[str, np.ndarray, float]:
    """The retreat's frame, direction and distance (the approach reversed when none)."""
    if options.retreat_direction is None:
        return options.grasp_frame, np.array([0.0, 0.0, -1.0]), options.approach_distance
    direction = np.asarray(options.retreat_direction, dtype=float)
    direction = direction / np.linalg.norm(direction)
    if options.retreat_frame == "world":
        return (
            options.root_frame,
            np.linalg.inv(options.base_pose)[:3, :3] @ direction,
            float(options.retreat_distance),
        )
    return options.grasp_frame, direction, float(options.retreat_distance)


def grasp_messages(
    g: GraspTable,
    options: MoveItOptions,
    *,
    world_frame: str | None = None,
    stamps: np.ndarray | None = None,
) -> list[dict[str, Any]]:
    """One ``moveit_msgs/Grasp`` mapping per row of ``g`` (ranked rows, best first).

    Args:
        g: The grasps, with ``dq``, ``rank`` and ``grasp_quality`` (finite).
        options: The run's MoveIt options.
        world_frame: ``grasp_pose`` in the world under this frame id (None:
            in the robot's root frame).
        stamps: Each message's header stamp [ns] (None: 0).
    """
    root, tool = options.root_frame, options.grasp_frame
    n = len(g)
    world = dq_to_matrix(np.asarray(g["dq"], dtype=float).reshape(n, 8))
    pose = world if world_frame is not None else np.linalg.inv(options.base_pose) @ world
    pos = pose[:, :3, 3]
    quat = Rotation.from_matrix(pose[:, :3, :3]).as_quat() if n else np.zeros((0, 4))
    quality = np.asarray(g["grasp_quality"], dtype=float)
    width = np.asarray(g["width"], dtype=float) if "width" in g else np.full(n, np.nan)
    joints = list(options.finger_joints)
    open_pos = [float(options.locked_joints[j]) for j in joints]
    hand_frame = options.hand_frame or tool
    d_app = options.approach_distance
    retreat_frame, retreat_dir, d_ret = _retreat(options)
    rank = np.asarray(g["rank"]) if "rank" in g else np.arange(1, n + 1)
    ns = np.zeros(n, np.int64) if stamps is None else np.asarray(stamps, np.int64)
    grasps = []
    for i in range(n):
        t = int(ns[i])
        closed = [0.5 * width[i] if np.isfinite(width[i]) else 0.0] * len(joints)
        x, y, z = (float(v) for v in pos[i])
        qx, qy, qz, qw = (float(v) for v in quat[i])
        grasps.append(
            {
                "id": f"rank_{int(rank[i])}",
                "pre_grasp_posture": _posture(hand_frame, joints, open_pos, 0.0, t),
                "grasp_posture": _posture(hand_frame, joints, closed, 1.0, t),
                "grasp_pose": {
                    "header": header(world_frame or root, t),
                    "pose": {
                        "position": {"x": x, "y": y, "z": z},
                        "orientation": {"x": qx, "y": qy, "z": qz, "w": qw},
                    },
                },
                "grasp_quality": float(quality[i]),
                "pre_grasp_approach": _translation(tool, np.array([0, 0, 1.0]), d_app, d_app, t),
                "post_grasp_retreat": _translation(retreat_frame, retreat_dir, d_ret, d_ret, t),
                "post_place_retreat": _translation("", np.zeros(3), 0.0, 0.0, t),
                "max_contact_force": 0.0,
                "allowed_touch_objects": [],
            }
        )
    return grasps


def arm_trajectory(
    options: MoveItOptions,
    q_pregrasp: np.ndarray,
    q: np.ndarray,
    q_retreat: np.ndarray,
    ns: int = 0,
) -> dict[str, Any]:
    """A ``trajectory_msgs/JointTrajectory`` mapping: approach -> grasp -> retreat.

    Args:
        options: The run's MoveIt options (``joint_names``, ``root_frame``).
        q_pregrasp: The configuration at the end of the approach (nq,), NaN: none.
        q: The grasp's configuration (nq,).
        q_retreat: The configuration at the end of the retreat (nq,), NaN: the
            approach reversed (ends at ``q_pregrasp``).
        ns: The header's stamp [ns].
    """
    if options.retreat_direction is None and np.isnan(q_retreat).all():
        q_retreat = q_pregrasp
    points = [
        _point(row, t)
        for row, t in zip((q_pregrasp, q, q_retreat), TRAJECTORY_TIMES, strict=True)
        if np.isfinite(row).all()
    ]
    return {
        "header": header(options.root_frame, ns),
        "joint_names": list(options.joint_names),
        "points": points,
    }
