"""What a config refers to outside itself (files, robot spec, meshes, viewer), checked first."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.config.gripper_spec import load_gripper
from gcm_pipeline.config.robot_spec import load_spec
from gcm_pipeline.config.run import Config, takes_config
from gcm_pipeline.errors import ConfigError, InputError, PublishError, RobotSpecError
from gcm_pipeline.geometry.meshes import MeshReadError, read_mesh
from gcm_pipeline.geometry.shapes import shape_geometry
from gcm_pipeline.outputs import live
from gcm_pipeline.pipeline.clouds import scene_clouds
from gcm_pipeline.robot.collision import (
    WorldShape,
    depth_below,
    depth_into,
    lift_out_of,
    object_shape,
    table_shape,
)
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.sources.file_object import warn_if_open
from gcm_pipeline.sources.grippers import GripperSpec, is_gripper_path

log = logging.getLogger(__name__)

#: An object reaching deeper than this into the table is warned about [m] (one standing
#: on it touches it: depth 0; a ``plane`` object, 1 mm thick, lying on it: 0.5 mm).
SUNK_DEPTH = 1e-3
#: How far below the table's top an object still counts as under the table [m].
_COLUMN_DEPTH = 1e3
#: Where each object shape has its pose (what a sunk object's warning reminds of).
_PLACED = {
    "box": "a box is centred on its pose",
    "sphere": "a sphere is centred on its pose",
    "cylinder": "a cylinder stands on its base at its pose",
    "plane": "a plane is centred on its pose",
    "mesh": "a mesh is placed as its file defines it",
}


def input_files(cfg: Config) -> dict[str, Path]:
    """The files a config reads, keyed by their dotted config key.

    ``candidates.path``, ``object.mesh``, ``objects.<i>.mesh``,
    ``environment.obstacles.<i>.mesh``, ``robot.spec`` when it is a spec file
    rather than a shipped name, and ``robot.tool`` / ``candidates.gripper`` when
    they are gripper files.
    """
    files: dict[str, Path] = {}
    if cfg.candidates.path is not None:
        files["candidates.path"] = Path(cfg.candidates.path)
    if cfg.object is not None and cfg.object.mesh is not None:
        files["object.mesh"] = Path(cfg.object.mesh)
    for i, obj in enumerate(cfg.objects or ()):
        if obj.mesh is not None:
            files[f"objects.{i}.mesh"] = Path(obj.mesh)
    for i, obstacle in enumerate(cfg.environment.obstacles):
        if obstacle.mesh is not None:
            files[f"environment.obstacles.{i}.mesh"] = Path(obstacle.mesh)
    for i, cloud in enumerate(cfg.environment.point_clouds):
        files[f"environment.point_clouds.{i}.path"] = Path(cloud.path)
        if cloud.segmap is not None:
            files[f"environment.point_clouds.{i}.segmap"] = Path(cloud.segmap)
    spec = cfg.robot.spec
    if spec.endswith((".yaml", ".yml")) or "/" in spec:
        files["robot.spec"] = Path(spec)
    for key, gripper in (
        ("robot.tool", cfg.robot.tool),
        ("candidates.gripper", cfg.candidates.gripper),
    ):
        if gripper is not None and is_gripper_path(gripper):
            files[key] = Path(gripper)
    return files


def check_input_files(cfg: Config) -> None:
    """Check that every file of :func:`input_files` is there and is a regular file.

    Raises:
        InputError: ``<key>: <what> not found: <path>`` (or not a regular file,
            or a symbolic link to nothing).
    """
    for key, path in input_files(cfg).items():
        try:
            found, there, link = path.is_file(), path.exists(), path.is_symlink()
        except (OSError, ValueError):
            found = there = link = False
        if not found:
            what = {
                "candidates.path": "grasp file",
                "robot.spec": "robot spec file",
                "robot.tool": "gripper file",
                "candidates.gripper": "gripper file",
            }.get(key, "cloud file" if ".point_clouds." in key else "mesh file")
            if there:  # a directory, a device (/dev/zero), a pipe
                raise InputError(f"{key}: {what} {path} is not a regular file")
            if link:  # ls shows it: "not found" would send the user looking
                raise InputError(
                    f"{key}: {what} {path} is a symbolic link that leads to no file "
                    "(dangling, or a loop of links)"
                )
            raise InputError(
                f"{key}: {what} not found: {path} (relative paths resolve against the "
                "config's folder)"
            )


def _check_gripper_meshes(gripper: GripperSpec, key: str) -> None:
    """Every mesh of a gripper file's shapes loads (else: the key, the file and the shape)."""
    assert gripper.tool is not None
    lists = [("collision", gripper.tool.collision)]
    if gripper.tool.visual is not gripper.tool.collision:
        lists.append(("visual", gripper.tool.visual))
    for kind, shapes in lists:
        for i, shape in enumerate(shapes):
            if shape.mesh is None:
                continue
            try:
                read_mesh(shape.mesh, shape.scale)
            except MeshReadError as exc:
                raise ConfigError(
                    f"{key}: gripper {str(gripper.path)!r}: {kind}[{i}].mesh: {exc}",
                    key=key,
                    path=gripper.path,
                ) from None


@takes_config
def warn_sunk_objects(
    cfg: Config, placed: WorldShape | None = None, name: str | None = None
) -> None:
    """Warn about the object reaching more than ``SUNK_DEPTH`` into the table, or under it.

    A box or sphere placed like the bottle (``xyz: [x, y, 0]``) sinks half into
    the table: the world is as written, but most of its grasps and moves then
    collide with the table, which a user seldom means. (With ``objects``, each
    object is the run's object once: :func:`~gcm_pipeline.pipeline.objects.target_config`.)
    ``placed``: the object's shape in the world if already built (a mesh is not
    read again). An object wholly under the slab (a sign slip in its z) is
    warned about too, with its lowest point's depth under the top. ``name``: the
    object's name in ``objects`` (the warning says which).
    """
    table, obj = cfg.environment.table, cfg.object
    if table is None or obj is None:
        return
    shape = _object_in_world(obj) if placed is None else placed
    # over or under the table's top face (its column, from the top far down)? then the
    # depth of its lowest point under the top: what to raise it by, whatever the slab
    column = table_shape(
        (table.size[0], table.size[1], _COLUMN_DEPTH), table.center_xy, table.height, np.eye(4)
    )
    if depth_into(shape, column) <= 0:
        return
    # the lift that clears the column: a part beside the table may hang lower
    depth = lift_out_of(shape, column, depth_below(shape, table.height) + 1e-6)
    if depth > SUNK_DEPTH:
        slab = table_shape(table.size, table.center_xy, table.height, np.eye(4))
        under = depth_into(shape, slab) <= 0  # wholly under the slab
        log.warning(
            "%s %s (its top at z = %g; %s): %s; to stand it on the table, raise its pose's "
            "z by %.4g",
            "the object" if name is None else f"object {name!r}",
            f"lies under the table, {1e3 * depth:.1f} mm below its top"
            if under
            else f"reaches {1e3 * depth:.1f} mm into the table",
            table.height,
            _PLACED.get(obj.shape, obj.shape),
            "the arm must reach through the table to grasp it"
            if under
            else "grasps near the table will collide with it",
            depth,
        )


def _object_in_world(obj: Any) -> WorldShape:
    """The config's object as a shape in the world frame (a mesh object's file is read)."""
    return object_shape(
        obj.shape, obj.dims, obj.pose.matrix(), np.eye(4), mesh=obj.mesh, scale=obj.scale
    )


@takes_config
def preflight(cfg: Config, *, viewer: bool = False, name: str | None = None) -> Robot:
    """Check, before any work, what the config refers to outside itself.

    ``gcm validate`` and ``gcm run`` (:meth:`Pipeline.run`) both call it:

    - every file the config reads exists (:func:`input_files`); relative
      paths were resolved against the config's folder;
    - ``candidates.gripper`` and ``robot.tool`` name a registry gripper or
      a valid gripper file; ``robot.tool`` is mounted on the spec's flange;
    - ``robot.spec`` names a shipped spec or a valid spec file whose model
      exists; the robot is built (kinematics, locked joints inside their
      ranges, a readable SRDF, collision meshes that load);
    - the ``environment.point_clouds`` read (:func:`~gcm_pipeline.pipeline.clouds.scene_clouds`,
      kept for the run);
    - the object and obstacle meshes load and have finite vertices; an object
      mesh that is not watertight is warned about (the contact model needs a
      closed mesh), and so is an object sunk into the table
      (:func:`warn_sunk_objects`);
    - with the live viewer requested (``viewer`` or ``publish.meshcat``) and a
      ``publish.zmq_url``, the meshcat server there answers within
      ``publish.connect_timeout_s``; without the viewer a ``zmq_url`` is unused,
      which is logged as a warning.

    Args:
        cfg: The config.
        viewer: The live viewer is requested (``gcm run --meshcat``).
        name: The object's name in ``objects`` (warnings say which object).

    Returns:
        The robot (the run uses it).

    Raises:
        RobotSpecError: ``robot.spec: ...``, unknown robot or invalid spec.
        InputError: ``<key>: file not found: <path>``, or a mesh that does not load.
        PublishError: ``publish.zmq_url: ...``, no meshcat server answers there.
    """
    check_input_files(cfg)
    for key, gripper in (
        ("candidates.gripper", cfg.candidates.gripper),
        ("robot.tool", cfg.robot.tool),
    ):
        if gripper is not None:  # a bad gripper file fails before any work, naming its key
            _check_gripper_meshes(load_gripper(gripper, key), key)
    try:
        robot = Robot(load_spec(cfg.robot.spec, cfg.robot.tool))
        robot.build_geometry("collision")
    except RobotSpecError as exc:
        raise type(exc)(f"robot.spec: {exc}") from exc
    obj = cfg.object
    # the object's shape once: its mesh loads here, and the table check reads it
    placed = None if obj is None else _object_in_world(obj)
    for i, o in enumerate(cfg.environment.obstacles):
        if o.shape == "mesh":
            where = f"environment.obstacles.{i}"
            shape_geometry("mesh", o.dims, mesh=o.mesh, scale=o.scale, where=where)
    scene_clouds(cfg.environment, cfg.object, cfg.candidates.camera_pose)  # read once, kept
    warn_sunk_objects(cfg, placed, name)
    if obj is not None and obj.mesh is not None and cfg.candidates.source != "antipodal":
        warn_if_open(Path(obj.mesh), obj.scale, f"object.mesh {obj.mesh}")  # the sampler warns
    pub = cfg.publish
    if pub.zmq_url is None:
        return robot
    if not (viewer or pub.meshcat):
        log.warning("publish.zmq_url is set but the live viewer is off; add --meshcat")
        return robot
    try:
        live.probe_server(pub.zmq_url, pub.connect_timeout_s)
    except PublishError as exc:
        raise PublishError(f"publish.zmq_url: {exc}") from exc
    return robot
