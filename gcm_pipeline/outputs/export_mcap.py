"""A run as a ROS 2 bag in one MCAP file, for ``ros2 bag`` and Foxglove.

The bag (MCAP storage, CDR serialisation, ``ros2msg`` schemas embedded, the
rosbag2 metadata record inside the file) has these topics, every message's
header in the frame named below and its stamp equal to its log time:

======================= ======================================= ================================
topic                   type                                    messages
======================= ======================================= ================================
``/tf_static``          ``tf2_msgs/msg/TFMessage``              one: ``world`` -> the robot's
                                                                root frame (the run's base pose)
``/scene_markers``      ``visualization_msgs/msg/MarkerArray``  one: the object, the table, the
                                                                obstacles and an arrow per grasp
                                                                (green reachable, red not; at
                                                                most :data:`MAX_ARROWS` each)
``/grasps``             ``moveit_msgs/msg/Grasp``               one per reachable grasp, best
                                                                first, ``grasp_pose`` in ``world``
``/grasp_trajectories`` ``trajectory_msgs/msg/JointTrajectory`` one per reachable grasp, best
                                                                first: approach -> grasp -> retreat
======================= ======================================= ================================

Log times start at the run's creation time (its ``.gcm.json``): the
transform and the markers first, then grasp ``k`` (rank ``k``) at
``start + k * GRASP_PERIOD_NS`` and its trajectory half a period later, so
every topic's log times increase strictly. The message types are those of
ROS 2 Humble (rosbags' type store), plus ``moveit_msgs/msg/Grasp`` and
``GripperTranslation`` from :data:`MOVEIT_MSGS` (moveit_msgs 2.x, the ``ros2``
branch). Writing needs the optional extra ``ros`` (rosbags,
:data:`ROS_INSTALL_HINT`).
"""

from __future__ import annotations

import functools
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from gcm_pipeline.errors import InputError
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.outputs.moveit_grasps import MoveItOptions, arm_trajectory, grasp_messages, header
from gcm_pipeline.outputs.scene_shapes import SceneShape, SceneTable
from gcm_pipeline.table import GraspTable

__all__ = [
    "GRASP_PERIOD_NS",
    "MAX_ARROWS",
    "MOVEIT_MSGS",
    "ROS_INSTALL_HINT",
    "TOPICS",
    "check_rosbags",
    "grasp_arrows",
    "WORLD_FRAME",
    "ros_message",
    "scene_markers",
    "typestore",
    "write_mcap",
]

ROS_INSTALL_HINT = 'pip install "gcm-pipeline[ros]"'

#: The frame of the grasp poses and the markers.
WORLD_FRAME = "world"

#: Log time between two grasps [ns].
GRASP_PERIOD_NS = 100_000_000

#: The bag's topics and their message types, in the order they are written.
TOPICS = {
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/scene_markers": "visualization_msgs/msg/MarkerArray",
    "/grasps": "moveit_msgs/msg/Grasp",
    "/grasp_trajectories": "trajectory_msgs/msg/JointTrajectory",
}

#: moveit_msgs' messages of the bag, as ROS 2 ``.msg`` field lists (the
#: interface of moveit_msgs 2.x, https://github.com/moveit/moveit_msgs, BSD-3-Clause).
MOVEIT_MSGS = {
    "moveit_msgs/msg/GripperTranslation": (
        "geometry_msgs/Vector3Stamped direction\nfloat32 desired_distance\nfloat32 min_distance\n"
    ),
    "moveit_msgs/msg/Grasp": (
        "string id\n"
        "trajectory_msgs/JointTrajectory pre_grasp_posture\n"
        "trajectory_msgs/JointTrajectory grasp_posture\n"
        "geometry_msgs/PoseStamped grasp_pose\n"
        "float64 grasp_quality\n"
        "GripperTranslation pre_grasp_approach\n"
        "GripperTranslation post_grasp_retreat\n"
        "GripperTranslation post_place_retreat\n"
        "float32 max_contact_force\n"
        "string[] allowed_touch_objects\n"
    ),
}

_REACHABLE_RGBA = (0.13, 0.69, 0.30, 0.9)
_UNREACHABLE_RGBA = (0.85, 0.16, 0.16, 0.6)
_OBJECT_RGBA = (0.85, 0.64, 0.25, 0.7)
_TABLE_RGBA = (0.78, 0.76, 0.73, 1.0)
_OBSTACLE_RGBA = (0.5, 0.5, 0.55, 0.8)
#: Most grasp arrows of each class (reachable, unreachable) in the scene's markers (about
#: 300 bytes each).
MAX_ARROWS = 20_000
#: A grasp arrow: length along the approach, ending at the grasp frame [m].
_ARROW_LENGTH = 0.05
#: Marker types (visualization_msgs/Marker).
_ARROW, _CUBE, _SPHERE, _CYLINDER, _MESH = 0, 1, 2, 3, 10


def _rosbags() -> Any:
    """The rosbags package (the optional extra ``ros``)."""
    try:
        import rosbags.interfaces
        import rosbags.rosbag2
        import rosbags.typesys
    except ImportError:
        raise InputError(f"the mcap export needs rosbags: {ROS_INSTALL_HINT}") from None
    return rosbags


@functools.cache
def _nodetype() -> Any:
    """The node kinds of rosbags' message fields (``Nodetype``), looked up once."""
    return _rosbags().typesys.store.Nodetype


def check_rosbags() -> None:
    """Raise :class:`InputError` (one line, :data:`ROS_INSTALL_HINT`) unless rosbags imports."""
    _rosbags()


def typestore() -> Any:
    """The ROS 2 Humble type store of rosbags, with :data:`MOVEIT_MSGS` registered."""
    typesys = _rosbags().typesys
    store = typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name, text in MOVEIT_MSGS.items():
        types.update(typesys.get_types_from_msg(text, name))
    store.register(types)
    return store


# ------------------------------------------------------------ mappings -> messages


def _default(store: Any, node: int, spec: Any) -> Any:
    """The default value of a field (0, "", an empty sequence, a default message)."""
    nodetype = _nodetype()
    if node == nodetype.NAME:
        return ros_message(store, spec, {})
    if node == nodetype.SEQUENCE:
        return _value(store, node, spec, [])
    if node == nodetype.ARRAY:
        (sub_node, sub_spec), length = spec
        return _value(store, node, spec, [_default(store, sub_node, sub_spec)] * length)
    return "" if spec[0] == "string" else (False if spec[0] == "bool" else 0)


def _value(store: Any, node: int, spec: Any, value: Any) -> Any:
    nodetype = _nodetype()
    if node == nodetype.NAME:
        return ros_message(store, spec, value)
    if node in (nodetype.SEQUENCE, nodetype.ARRAY):
        (sub_node, sub_spec), _ = spec
        if sub_node == nodetype.BASE and sub_spec[0] != "string":
            dtype = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8, "octet": np.uint8}
            return np.asarray(value, dtype=dtype.get(sub_spec[0], sub_spec[0]))
        return [_value(store, sub_node, sub_spec, v) for v in value]
    kind = spec[0]
    if kind == "string":
        return str(value)
    if kind.startswith("float"):
        return float(value)
    return bool(value) if kind == "bool" else int(value)


def ros_message(store: Any, typename: str, data: Mapping[str, Any]) -> Any:
    """A rosbags message of ``typename`` from a mapping of its fields (others: defaults).

    Raises:
        KeyError: ``data`` has a field the message does not (a bug here).
    """
    msgdef = store.get_msgdef(typename)
    names = {name for name, _ in msgdef.fields}
    unknown = set(data) - names
    if unknown:
        raise KeyError(f"{typename} has no field {sorted(unknown)}")
    return msgdef.cls(
        **{
            name: _value(store, spec[0], spec[1], data[name])
            if name in data
            else _default(store, spec[0], spec[1])
            for name, spec in msgdef.fields
        }
    )


# ------------------------------------------------------------ scene


def _pose(m: np.ndarray) -> dict[str, Any]:
    x, y, z = (float(v) for v in m[:3, 3])
    qx, qy, qz, qw = (float(v) for v in Rotation.from_matrix(m[:3, :3]).as_quat())
    return {
        "position": {"x": x, "y": y, "z": z},
        "orientation": {"x": qx, "y": qy, "z": qz, "w": qw},
    }


def _rgba(c: Sequence[float]) -> dict[str, float]:
    return dict(zip("rgba", (float(v) for v in c), strict=True))


def _xyz(v: Sequence[float]) -> dict[str, float]:
    return dict(zip("xyz", (float(c) for c in v), strict=True))


def _shape_marker(shape: SceneShape) -> dict[str, Any]:
    """A scene shape's marker fields (type, pose, scale, mesh): one branch per shape kind."""
    pose = np.array(shape.pose, dtype=float)
    if shape.shape == "cylinder":
        r, h = float(shape.radius), float(shape.height)
        pose = pose @ np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, h / 2], [0, 0, 0, 1.0]])
        return {"type": _CYLINDER, "pose": _pose(pose), "scale": _xyz((2 * r, 2 * r, h))}
    if shape.shape == "sphere":
        d = 2 * float(shape.radius)
        return {"type": _SPHERE, "pose": _pose(pose), "scale": _xyz((d, d, d))}
    if shape.shape == "box":
        return {"type": _CUBE, "pose": _pose(pose), "scale": _xyz(shape.size)}
    if shape.shape == "plane":  # a thin box, as the collision world models it
        return {"type": _CUBE, "pose": _pose(pose), "scale": _xyz((*shape.size, 0.002))}
    s = float(shape.scale)
    return {
        "type": _MESH,
        "pose": _pose(pose),
        "scale": _xyz((s, s, s)),
        "mesh_resource": Path(shape.mesh).resolve().as_uri(),
    }


def _marker(ns_name: str, marker_id: int, stamp_ns: int, rgba: Sequence[float], **fields: Any):
    return {
        "header": header(WORLD_FRAME, stamp_ns),
        "ns": ns_name,
        "id": marker_id,
        "action": 0,
        "color": _rgba(rgba),
        **fields,
    }


def scene_markers(
    everything: GraspTable,
    obj: SceneShape | None,
    table: SceneTable | None,
    obstacles: Sequence[SceneShape],
    stamp_ns: int,
) -> dict[str, Any]:
    """The scene as a ``visualization_msgs/MarkerArray`` mapping.

    Namespaces ``object``, ``table``, ``obstacles`` (id: the obstacle's index),
    ``grasps_reachable`` (id: the rank) and ``grasps_unreachable`` (id: the
    row in ``grasps.csv``): :func:`grasp_arrows`.
    """
    markers = []
    if obj is not None:
        markers.append(_marker("object", 0, stamp_ns, _OBJECT_RGBA, **_shape_marker(obj)))
    if table is not None:
        sx, sy, sz = table.size
        centre = np.eye(4)
        centre[:3, 3] = (*table.center_xy, table.height - sz / 2)
        fields = {"type": _CUBE, "pose": _pose(centre), "scale": _xyz((sx, sy, sz))}
        markers.append(_marker("table", 0, stamp_ns, _TABLE_RGBA, **fields))
    for i, obstacle in enumerate(obstacles):
        fields = _shape_marker(obstacle)
        markers.append(_marker("obstacles", i, stamp_ns, _OBSTACLE_RGBA, **fields))
    return {"markers": markers + grasp_arrows(everything, stamp_ns)}


def grasp_arrows(everything: GraspTable, stamp_ns: int) -> list[dict[str, Any]]:
    """An arrow marker per grasp, at most :data:`MAX_ARROWS` of each class.

    An arrow ends at the grasp frame's origin and points along its approach
    axis (+z). Reachable grasps (green, id: the rank; the best-ranked when
    there are more than :data:`MAX_ARROWS`), unreachable ones (red, id: the
    row; evenly spaced rows when there are more).
    """
    n = len(everything)
    world = dq_to_matrix(np.asarray(everything["dq"], dtype=float).reshape(n, 8))
    tip = world[:, :3, 3]
    tail = tip - _ARROW_LENGTH * world[:, :3, 2]
    reachable = np.asarray(everything["reachable"], dtype=bool)
    rank = np.asarray(everything["rank"]) if "rank" in everything else np.zeros(n, int)
    good = np.flatnonzero(reachable)
    good = good[np.argsort(np.where(rank[good] > 0, rank[good], n + good), kind="stable")]
    bad = np.flatnonzero(~reachable)
    if len(bad) > MAX_ARROWS:
        bad = bad[np.linspace(0, len(bad) - 1, MAX_ARROWS).astype(int)]
    arrow = {"type": _ARROW, "pose": _pose(np.eye(4)), "scale": _xyz((0.002, 0.005, 0.008))}
    markers = []
    for ns_name, rows, rgba in (
        ("grasps_reachable", good[:MAX_ARROWS], _REACHABLE_RGBA),
        ("grasps_unreachable", bad, _UNREACHABLE_RGBA),
    ):
        for i in rows:
            marker_id = int(rank[i]) if reachable[i] and rank[i] > 0 else int(i)
            points = [_xyz(tail[i]), _xyz(tip[i])]
            markers.append(_marker(ns_name, marker_id, stamp_ns, rgba, **arrow, points=points))
    return markers


def _tf_static(options: MoveItOptions, stamp_ns: int) -> dict[str, Any]:
    pose = _pose(np.asarray(options.base_pose, dtype=float))
    return {
        "transforms": [
            {
                "header": header(WORLD_FRAME, stamp_ns),
                "child_frame_id": options.root_frame,
                "transform": {"translation": pose["position"], "rotation": pose["orientation"]},
            }
        ]
    }


# ------------------------------------------------------------ the bag


def _latched(rosbags: Any) -> list[Any]:
    """QoS of a latched topic (transient local), as ``ros2 bag play`` offers it."""
    i = rosbags.interfaces
    zero = i.QosTime(0, 0)
    return [
        i.Qos(
            i.QosHistory.KEEP_LAST,
            1,
            i.QosReliability.RELIABLE,
            i.QosDurability.TRANSIENT_LOCAL,
            zero,
            zero,
            i.QosLiveliness.AUTOMATIC,
            zero,
            False,
        )  # fmt: skip
    ]


def write_mcap(
    path: Path,
    ranked: GraspTable,
    everything: GraspTable,
    configurations: Mapping[str, np.ndarray],
    options: MoveItOptions,
    scene: tuple[SceneShape | None, SceneTable | None, Sequence[SceneShape]],
    start_ns: int,
    name: str = "grasps.mcap",
) -> None:
    """Write the bag into the new file ``path`` (the module's topics).

    Args:
        path: The ``.mcap`` file to create.
        ranked: The reachable grasps, best first, with ``grasp_quality``.
        everything: Every grasp of the run (the markers' arrows).
        configurations: ``q``, ``q_pregrasp``, ``q_retreat`` of ``ranked`` (K, nq).
        options: The run's MoveIt options (frames, approach, retreat, joints).
        scene: The object, the table and the obstacles.
        start_ns: The first log time [ns since the epoch].
        name: The file's final name (the bag's metadata names it).
    """
    rosbags = _rosbags()
    store = typestore()
    k = len(ranked)
    stamps = start_ns + GRASP_PERIOD_NS * np.arange(1, k + 1, dtype=np.int64)
    grasps = grasp_messages(ranked, options, world_frame=WORLD_FRAME, stamps=stamps)
    work = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    bag = work / Path(name).stem  # rosbags writes the folder bag/ with bag/<stem>.mcap
    writer = rosbags.rosbag2.Writer(
        bag, version=9, storage_plugin=rosbags.rosbag2.StoragePlugin.MCAP
    )
    try:
        with writer:
            conns = {
                topic: writer.add_connection(
                    topic,
                    msgtype,
                    typestore=store,
                    offered_qos_profiles=_latched(rosbags) if topic != "/grasps" else (),
                )
                for topic, msgtype in TOPICS.items()
            }

            def put(topic: str, ns: int, data: Mapping[str, Any]) -> None:
                msg = ros_message(store, TOPICS[topic], data)
                writer.write(conns[topic], ns, store.serialize_cdr(msg, TOPICS[topic]))

            put("/tf_static", start_ns, _tf_static(options, start_ns))
            put("/scene_markers", start_ns + 1, scene_markers(everything, *scene, start_ns + 1))
            for i in range(k):
                t = int(stamps[i])
                put("/grasps", t, grasps[i])
                q = [np.asarray(configurations[c][i], dtype=float) for c in _CONFIGURATIONS]
                half = t + GRASP_PERIOD_NS // 2
                put("/grasp_trajectories", half, arm_trajectory(options, q[0], q[1], q[2], half))
        (bag / f"{bag.name}.mcap").replace(path)
    finally:
        shutil.rmtree(work, ignore_errors=True)


#: The configurations of an arm trajectory, in ``configurations.npz``.
_CONFIGURATIONS = ("q_pregrasp", "q", "q_retreat")
