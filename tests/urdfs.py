"""Small URDFs written by tests: a UR5-like 6R arm made of primitives, with knobs for the
quirks users' URDFs have (a joint named like a link, continuous joints, huge limits,
relative or ``package://`` meshes)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

# (joint, parent link, child link, origin xyz, origin rpy, axis): the UR5 of example-robot-data
UR5_JOINTS = [
    ("shoulder_pan_joint", "base_link", "shoulder_link", "0 0 0.089159", "0 0 0", "0 0 1"),
    ("shoulder_lift_joint", "shoulder_link", "upper_arm_link", "0 0.13585 0", "0 1.5707963 0",
     "0 1 0"),
    ("elbow_joint", "upper_arm_link", "forearm_link", "0 -0.1197 0.425", "0 0 0", "0 1 0"),
    ("wrist_1_joint", "forearm_link", "wrist_1_link", "0 0 0.39225", "0 1.5707963 0", "0 1 0"),
    ("wrist_2_joint", "wrist_1_link", "wrist_2_link", "0 0.093 0", "0 0 0", "0 0 1"),
    ("wrist_3_joint", "wrist_2_link", "wrist_3_link", "0 0 0.09465", "0 0 0", "0 1 0"),
]  # fmt: skip
# a collision cylinder per link: (radius, length, xyz, rpy)
SHAPES = {
    "base_link": (0.06, 0.05, "0 0 0.025", "0 0 0"),
    "shoulder_link": (0.06, 0.12, "0 0 0", "0 0 0"),
    "upper_arm_link": (0.05, 0.30, "0 0 0.2125", "0 0 0"),
    "forearm_link": (0.04, 0.28, "0 0 0.196", "0 0 0"),
    "wrist_1_link": (0.035, 0.10, "0 0.093 0", "1.5707963 0 0"),
    "wrist_2_link": (0.035, 0.09, "0 0 0.09465", "0 0 0"),
    "wrist_3_link": (0.03, 0.04, "0 0.06 0", "1.5707963 0 0"),
}


def arm_urdf(
    *,
    joint_type: str | dict[str, str] = "revolute",
    limits: tuple[float, float] | None = (-2 * math.pi, 2 * math.pi),
    flange_joint: str = "tool0_joint",
    mesh: str | None = None,
    mesh_link: str = "wrist_3_link",
    geometry: dict[str, str] | None = None,
    name: str = "arm",
) -> str:
    """URDF text of a UR5-like arm ending in a ``tool0`` flange (z out of the flange).

    Args:
        joint_type: Type of every arm joint, or joint name -> type.
        limits: ``<limit lower upper>`` of every arm joint (None: no lower/upper).
        flange_joint: Name of the fixed joint to ``tool0`` (``"tool0"``: a joint and a
            link of one name).
        mesh: A mesh filename used as ``mesh_link``'s visual and collision geometry
            instead of its cylinder.
        geometry: Link -> the ``<geometry>`` element's content of its visual and
            collision (e.g. ``<box size="0.1 0.1 0.2"/>``), instead of its cylinder.
        name: The robot's name.
    """
    out = [f'<?xml version="1.0"?>\n<robot name="{name}">']
    for link, (r, length, xyz, rpy) in SHAPES.items():
        if mesh is not None and link == mesh_link:
            geom = f'<geometry><mesh filename="{mesh}"/></geometry>'
        elif geometry is not None and link in geometry:
            geom = f"<geometry>{geometry[link]}</geometry>"
        else:
            geom = f'<geometry><cylinder radius="{r}" length="{length}"/></geometry>'
        out.append(
            f'  <link name="{link}">\n'
            f'    <visual><origin xyz="{xyz}" rpy="{rpy}"/>{geom}</visual>\n'
            f'    <collision><origin xyz="{xyz}" rpy="{rpy}"/>{geom}</collision>\n'
            f'    <inertial><mass value="1"/>'
            f'<inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>\n'
            "  </link>"
        )
    for joint, parent, child, xyz, rpy, axis in UR5_JOINTS:
        kind = joint_type if isinstance(joint_type, str) else joint_type.get(joint, "revolute")
        lim = ""
        if limits is not None:
            lim = f'<limit lower="{limits[0]!r}" upper="{limits[1]!r}" effort="28" velocity="3.2"/>'
        elif kind != "fixed":
            lim = '<limit effort="28" velocity="3.2"/>'
        out.append(
            f'  <joint name="{joint}" type="{kind}"><parent link="{parent}"/>'
            f'<child link="{child}"/><origin xyz="{xyz}" rpy="{rpy}"/>'
            f'<axis xyz="{axis}"/>{lim}</joint>'
        )
    out.append('  <link name="tool0"/>')
    out.append(
        f'  <joint name="{flange_joint}" type="fixed"><parent link="wrist_3_link"/>'
        '<child link="tool0"/><origin xyz="0 0.0823 0" rpy="-1.5707963 0 0"/></joint>'
    )
    out.append("</robot>\n")
    return "\n".join(out)


def write_concave_forearm(path: Path) -> None:
    """An STL forearm for ``arm_urdf(mesh=..., mesh_link="forearm_link")``: concave.

    The cylinder of ``arm_urdf`` with a block beside it (two solids in one mesh).
    """
    import trimesh

    path.parent.mkdir(parents=True, exist_ok=True)
    rod = trimesh.creation.cylinder(radius=0.04, height=0.28, sections=24)
    block = trimesh.creation.box(extents=[0.05, 0.05, 0.08])
    block.apply_translation([0.07, 0.0, 0.08])
    trimesh.util.concatenate([rod, block]).export(path)


def write_arm(folder: Path, spec_extra: str = "", *, urdf_name: str = "arm.urdf", **kw) -> Path:
    """Write ``arm.urdf`` and ``spec.yaml`` (grasp frame ``tool0``) in ``folder``; the spec."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / urdf_name).write_text(arm_urdf(**kw))
    spec = folder / "spec.yaml"
    spec.write_text(f"name: arm\nmodel: {{urdf: {urdf_name}}}\ngrasp_frame: tool0\n" + spec_extra)
    return spec


#: The links of :func:`write_mixed_arm` other than its cylinders: a sphere, boxes and a
#: mesh (the concave forearm of :func:`write_concave_forearm` is the other mesh).
MIXED_GEOMETRY = {
    "shoulder_link": '<sphere radius="0.065"/>',
    "wrist_1_link": '<box size="0.07 0.07 0.12"/>',
    "wrist_2_link": '<mesh filename="meshes/wrist_2.stl"/>',
    "wrist_3_link": '<box size="0.07 0.07 0.04"/>',
}


def write_mixed_arm(folder: Path) -> Path:
    """:func:`write_arm` with every kind of URDF geometry, meshes as STL files; the spec.

    Cylinders (base, upper arm), a sphere (shoulder), the concave mesh forearm of
    :func:`write_concave_forearm`, boxes (wrists 1 and 3, the gripper) and a convex
    mesh (wrist 2, a stretched icosphere): self pairs of two polytopes (the forearm
    against wrists 2 and 3, wrist 1 against wrist 3), two of them against a box.
    """
    import trimesh

    write_concave_forearm(folder / "meshes" / "forearm.stl")
    wrist = trimesh.creation.icosphere(subdivisions=1, radius=0.04)
    wrist.vertices *= [1.0, 1.0, 1.4]
    wrist.export(folder / "meshes" / "wrist_2.stl")
    return write_arm(
        folder, mesh="meshes/forearm.stl", mesh_link="forearm_link", geometry=MIXED_GEOMETRY
    )


def bottle_checker(name: str, folder: Path) -> Any:
    """The collision checker of the bottle scene for ``panda``, ``ur5_robotiq``,
    ``user_arm`` or ``user_mixed``.

    ``user_arm``: :func:`write_arm` with :func:`write_concave_forearm` as its forearm's
    mesh; ``user_mixed``: :func:`write_mixed_arm`; written in ``folder``.
    """
    from gcm_pipeline import pipeline

    cfg = _bottle_config(name, folder)
    return pipeline.make_checker(pipeline.robot_from_config(cfg), cfg.environment, cfg.object)


def level_columns(checker: Any, level: str) -> list[tuple[Any, int, int]]:
    """The columns of a broad-phase level (a ``Screen`` attribute: ``self_hulls``,
    ``self_boxes``, ``cylinders``) in the grasp and approach screens: [(screen, column,
    pair)]."""
    from gcm_pipeline.robot.collision.pairs import MODE_BIT

    out = []
    for mode in ("grasp", "approach"):
        screen = checker._screens[MODE_BIT[mode]]
        out += [(screen, k, int(screen.pairs[k])) for k in getattr(screen, level)]
    return out


def level_case(name: str, tmp_path_factory: Any, level: str, seed: int, keep: int) -> Any:
    """``(name, checker, near, plain)`` for a level's tests in the bottle scene.

    ``near``: per column of the level, ``keep`` of 3,000 random configurations and both
    sides of that column's pair's contact (``pair_contact``); ``plain``: the same checker
    with the level's columns removed.
    """
    import numpy as np
    from helpers import pair_contact

    checker = bottle_checker(name, tmp_path_factory.mktemp("arm"))
    q = checker.robot.random_configurations(3000, seed)
    near = {
        c: np.concatenate([q[:keep], pair_contact(checker, q, c, most=100)])
        for *_, c in level_columns(checker, level)
    }
    plain = bottle_checker(name, tmp_path_factory.mktemp("arm"))
    for screen in plain._screens.values():
        getattr(screen, level).clear()
    return name, checker, near, plain


def assert_same_without_level(case: Any, mode: str, numpy_code: Any, reasons: set[str]) -> None:
    """A :func:`level_case`'s checker decides as its ``plain`` twin and as the NumPy code on
    every ``near`` configuration in ``mode``, and gives at least ``reasons``."""
    import numpy as np

    _, checker, near, plain = case
    q = np.concatenate(list(near.values()))
    got = checker.check(q, mode)
    np.testing.assert_array_equal(got, plain.check(q, mode))
    np.testing.assert_array_equal(numpy_code(checker.check, q, mode), got)
    assert reasons <= set(got.tolist())


def _bottle_config(name: str, folder: Path) -> Any:
    from helpers import CONFIGS

    from gcm_pipeline.config import load_config

    if name == "panda":
        return load_config(CONFIGS / "bottle_side.yaml")
    if name == "ur5_robotiq":
        return load_config(CONFIGS / "bottle_side_ur5.yaml")
    if name == "user_mixed":
        spec = write_mixed_arm(folder)
    else:
        write_concave_forearm(folder / "meshes" / "forearm.stl")
        spec = write_arm(folder, mesh="meshes/forearm.stl", mesh_link="forearm_link")
    return load_config(CONFIGS / "bottle_side.yaml", [f"robot.spec={spec}"])
