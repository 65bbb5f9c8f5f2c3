"""``gcm robot SPEC``: what a robot spec configures, and its scene.

Joints, limits, frames, tool and collision pairs; ``--out FILE`` writes the
scene of the robot at home.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def add_parsers(sub: Any, common: argparse.ArgumentParser) -> None:
    """Add ``robot`` to the ``gcm`` subcommands."""
    robot = sub.add_parser(
        "robot",
        parents=[common],
        help="print a robot spec's joints, limits, frames, tool and collision pairs",
        description="Load a robot spec (a shipped name such as panda or ur5, or a YAML "
        "file) and print its joints (type, limits, home), its frames (base, flange, grasp "
        "frame), its tool and its self-collision pairs; --out writes an HTML scene of the "
        "robot at home with its tool and the grasp (TCP) frame drawn as a gripper glyph.",
    )
    robot.add_argument("spec", metavar="SPEC", help="robot spec: a shipped name or a YAML file")
    robot.add_argument("--out", type=Path, metavar="FILE", help="write the scene (HTML) here")


def _xyz_rpy(m: Any) -> str:
    """A pose as ``xyz [..] m, rpy [..] deg``."""
    from scipy.spatial.transform import Rotation

    xyz = ", ".join(f"{v:.4f}" for v in m[:3, 3])
    rpy = ", ".join(f"{v:.1f}" for v in Rotation.from_matrix(m[:3, :3]).as_euler("xyz", True))
    return f"xyz [{xyz}] m, rpy [{rpy}] deg"


def _shape_text(shape: Any) -> str:
    if shape.shape == "box":
        size = " x ".join(f"{v:g}" for v in shape.size)
    elif shape.shape in ("cylinder", "capsule"):
        size = f"r {shape.size[0]:g} l {shape.size[1]:g}"
    elif shape.shape == "sphere":
        size = f"r {shape.size[0]:g}"
    else:
        size = f"{shape.mesh.name}" + (f" scale {shape.scale[0]:g}" if shape.scale[0] != 1 else "")
    finger = f", finger {shape.finger}" if shape.finger else ""
    return f"{shape.name} ({shape.shape} {size}{finger})"


def robot_report(robot: Any) -> list[str]:
    """The lines ``gcm robot`` prints about a robot (see :func:`_cmd_robot`)."""
    return [*_joint_lines(robot), *_frame_and_tool_lines(robot), *_collision_lines(robot)]


def _joint_lines(robot: Any) -> list[str]:
    """The robot's name, model source, joints (type, limits, home), locks and limit margin."""
    spec = robot.spec
    out = [
        f"robot {robot.name} ({spec.path})" + (f": {spec.description}" if spec.description else "")
    ]
    source = (
        f"example-robot-data {spec.example_robot_data!r}"
        if spec.example_robot_data
        else f"robot_descriptions {spec.robot_descriptions!r}"
        if spec.robot_descriptions
        else "URDF"
    )
    out.append(f"  model        {source}: {robot.urdf_path}")
    if robot.srdf_path is not None:
        out.append(f"               SRDF {robot.srdf_path}")
    out.append(f"  joints       {robot.nq} arm joints [rad or m]")
    width = max(len(n) for n in robot.joint_names)
    out.append(f"    {'name':<{width}}  {'type':<24}  {'lower':>8}  {'upper':>8}  {'home':>8}")
    model = robot.model
    for i, name in enumerate(robot.joint_names):
        jm = model.joints[i + 1]
        kind = "prismatic" if jm.shortname().startswith("JointModelP") else "revolute"
        if name in robot.continuous_joints:
            kind = "continuous (as revolute)"
        lo, hi, home = robot.lower[i], robot.upper[i], robot.home[i]
        out.append(f"    {name:<{width}}  {kind:<24}  {lo:8.4f}  {hi:8.4f}  {home:8.4f}")
    if robot.continuous_joints:
        out.append(
            "               continuous joints get [-2pi, 2pi] unless joint_limits gives a range"
        )
    if robot.locked_values:
        mimic = robot.urdf.mimic
        locked = ", ".join(
            f"{k} = {v:g}" + (f" (mimics {mimic[k].leader})" if k not in spec.locked_joints else "")
            for k, v in robot.locked_values.items()
        )
        out.append(f"  locked       {locked}")
    out.append(
        f"  limit margin {spec.limit_margin:g} rad (each revolute range above shrinks by it "
        "on both sides; continuous joints keep two turns)"
    )
    return out


def _frame_and_tool_lines(robot: Any) -> list[str]:
    """The base, flange and grasp frames, the reach and the tool."""
    import pinocchio as pin

    from gcm_pipeline.robot.urdf import frame_kind

    spec = robot.spec
    out: list[str] = []
    fm = robot.full_model
    out.append(
        f"  frames       base {robot.urdf.root_link} (the URDF's root link; poses are in it)"
    )
    gid = robot.full_grasp_frame_id
    parent = int(fm.frames[gid].parentFrame)
    while fm.frames[parent].type != pin.FrameType.BODY and parent > 0:
        parent = int(fm.frames[parent].parentFrame)
    tool = spec.tool
    if tool is not None:
        out.append(f"               flange {tool.flange} (the tool is mounted on it)")
    home = robot.fk(robot.home)[0]
    kind = frame_kind(fm, gid)
    on = "fixed to" if kind == "link" else "on link"
    out.append(
        f"               grasp frame {robot.grasp_frame} ({kind} {on} {fm.frames[parent].name}); "
        f"at home: {_xyz_rpy(home)}"
    )
    shoulder = ", ".join(f"{v:.3f}" for v in robot.shoulder)
    out.append(f"  reach        {robot.max_reach:.3f} m from the shoulder [{shoulder}]")
    if tool is None:
        out.append("  tool         none (the grasp frame is the model's own)")
    else:
        out.append(f"  tool         {tool.name} on {tool.flange}: mount {_xyz_rpy(tool.mount)}")
        out.append(f"               TCP in the tool frame: {_xyz_rpy(tool.tcp)}")
        if tool.opening is not None:
            axis = ", ".join(f"{v:g}" for v in tool.axis)
            out.append(f"               fingers open {tool.opening:g} m along [{axis}]")
        if tool.collision:
            shapes = ", ".join(_shape_text(s) for s in tool.collision)
            out.append(f"               collision shapes: {shapes}")
        elif robot.model_hand_links:
            links = ", ".join(robot.model_hand_links)
            out.append(
                "               TCP only: no collision shapes; the hand is the model's links, "
                f"collision-checked: {links}"
            )
        else:
            out.append(
                "               TCP only: no collision shapes, the hand is not collision-checked"
            )
    return out


def _collision_lines(robot: Any) -> list[str]:
    """The collision shapes, the self-collision pairs checked and the link pairs left out."""
    import numpy as np

    from gcm_pipeline.robot.collision import CollisionChecker, gripper_links

    model = robot.model
    tool = robot.spec.tool
    out: list[str] = []
    checker = CollisionChecker(robot, (), self_collision=True)
    links = checker.link_names
    kinds = np.asarray(checker.pair_kind)
    pairs = [
        p for p, k in zip(checker.geom_model.collisionPairs, kinds, strict=True) if k == "self"
    ]
    checked = {frozenset((links[int(p.first)], links[int(p.second)])) for p in pairs}
    joint_of = {
        links[i]: int(g.parentJoint)
        for i, g in enumerate(checker.geom_model.geometryObjects[: checker.n_robot_geoms])
    }
    names = sorted(set(links), key=list(links).index)
    excluded = []
    for a_i, a in enumerate(names):
        for b in names[a_i + 1 :]:
            if frozenset((a, b)) in checked:
                continue
            ja, jb = joint_of[a], joint_of[b]
            if ja == jb:
                why = "one body"
            elif model.parents[ja] == jb or model.parents[jb] == ja:
                why = "adjacent"
            else:
                why = "SRDF"
            excluded.append(f"{a}-{b} ({why})")
    grip = sorted(gripper_links(robot))
    if robot.dropped_links:
        out.append(f"  dropped      collision geometry of {', '.join(sorted(robot.dropped_links))}")
    out.append(
        f"  collision    {checker.n_robot_geoms} shapes on {len(names)} links; gripper: "
        f"{', '.join(grip) or '(none)'}"
        + (" + the tool's shapes" if tool and tool.collision else "")
    )
    out.append(
        f"               {len(pairs)} self-collision pairs checked ({len(checked)} link pairs)"
    )
    line = f"{' ' * 15}{len(excluded)} link pairs not checked:"
    for i, item in enumerate(excluded or ["(none)"]):  # whole items per line
        item += "," if i < len(excluded) - 1 else ""
        if len(line) + 1 + len(item) > 100:
            out.append(line)
            line = " " * 17 + item
        else:
            line += " " + item
    out.append(line)
    return out


def _cmd_robot(args: argparse.Namespace) -> int:
    import numpy as np

    from gcm_pipeline.config.robot_spec import load_robot
    from gcm_pipeline.config.run import Config
    from gcm_pipeline.geometry.dualquat import dq_from_matrix
    from gcm_pipeline.outputs.html import write_scene_html
    from gcm_pipeline.pipeline.outputs import scene_options
    from gcm_pipeline.table import GraspTable

    robot = load_robot(args.spec)
    for line in robot_report(robot):
        print(line)
    if args.out is not None:
        spec = str(robot.spec.path)
        cfg = Config.from_dict(
            {
                "robot": {"spec": spec},
                "candidates": {"source": "file", "path": spec},
                "environment": {"table": None},
                "ranking": {"top_k": 1},
            },
            source="gcm robot",
        )
        # the grasp frame at home, drawn as the scene's gripper glyph (the robot at home)
        tcp = GraspTable(
            {
                "dq": dq_from_matrix(robot.fk(robot.home)),
                "reachable": np.ones(1, bool),
                "rank": np.ones(1, np.int64),
                "q": robot.home[None],
                "manipulability": np.ones(1),
            }
        )
        info = write_scene_html(args.out, tcp, None, robot, scene_options(cfg))
        print(
            f"  scene        {args.out}: {', '.join(info.paths)} ({info.meshcat_objects} meshcat "
            "objects; the robot at home, its grasp frame drawn as a gripper glyph)"
        )
    return 0


COMMANDS = {"robot": _cmd_robot}
