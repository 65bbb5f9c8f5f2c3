"""Gripper registry: grasp-file frame conventions mapped onto the robot's grasp frame.

A grasp synthesiser writes the pose of *its* gripper frame; the pipeline
needs the pose of the robot's grasp frame (for the Panda ``panda_hand_tcp``:
origin midway between the fingertips, z = approach, fingers closing along y).
The map between the two depends on the gripper and on the file's convention;
a :class:`GripperSpec` holds it, with the gripper's opening limit and finger
depth (used by the antipodal sampler).

Conventions (``T_tool = T_file @ to_tool``; back: ``T_file = T_tool @ from_tool``):

=============== ============================================= =====================
convention      file frame                                    used by
=============== ============================================= =====================
``base``        origin at the hand's base (``panda_hand``),   ACRONYM, GraspGen,
                z = approach, fingers closing along x; the    Contact-GraspNet
                fingertip midpoint is ``base_to_tcp`` along z
``center``      origin at the grasp centre, x = approach,     GraspNet-1Billion,
                y = closing (``width``), z = the finger       AnyGrasp
                ``height`` axis; the fingertips reach
                ``depth`` (per grasp) past the centre along
                x, so the robot's grasp frame (``finger_tip``
                behind its fingertips) is ``depth -
                finger_tip`` past the centre
=============== ============================================= =====================

Sources for the conventions: ACRONYM's Franka gripper has finger control
points at x = +-0.041 m and the hand's base frame at the origin; GraspGen's
gripper description (``docs/GRIPPER_DESCRIPTION.md``: approach +z, fingers
closing along x, ``depth`` = base link to TCP) and its Franka config;
Contact-GraspNet's ``build_6d_grasp`` (rotation columns = [closing
direction, approach x closing, approach], origin = contact + width/2 along
the closing direction - 0.1034 m along the approach); graspnetAPI's
``plot_gripper_pro_max`` (fingers span x in [-0.024, depth], width along y,
height along z) and its 17-value grasp rows.

A file's gripper is, in this order: ``candidates.gripper``; the gripper the
file names (ACRONYM's ``gripper/type``, GraspGen's ``gripper``), which the
registry must know; the format's dataset gripper (:data:`DATASET_GRIPPERS`);
the robot's tool (``robot.tool``). A file with none of these or naming an
unknown gripper is refused with the choices (:func:`choose_gripper`); the
choice is logged and kept in ``summary.json``'s ``grasp_frame`` (:class:`GripperChoice`).

The registry is data: one YAML file per gripper in ``gcm_pipeline/grippers/``
(:func:`shipped_grippers`), or a user's own file, read and validated by
:mod:`gcm_pipeline.config.gripper_spec` into a :class:`GripperSpec`. The same
definition maps grasp files (:meth:`GripperSpec.to_tool`), sizes the antipodal
sampler's hand and, as :attr:`GripperSpec.tool`, is the tool mounted on an
arm's flange (``robot.tool``).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gcm_pipeline.errors import ConfigError, InputError, choice_error, unknown_choice

if TYPE_CHECKING:  # the robot layer loads coal: configs read the gripper names without it
    from gcm_pipeline.robot.tool import ToolSpec

__all__ = [
    "CONVENTIONS",
    "DATASET_GRIPPERS",
    "KINDS",
    "GripperChoice",
    "GripperSpec",
    "check_gripper_ref",
    "choose_gripper",
    "find_gripper",
    "is_gripper_path",
    "registry_dir",
    "shipped_grippers",
]

log = logging.getLogger(__name__)

#: Frame conventions of grasp files (see the module docstring).
CONVENTIONS = ("base", "center")
#: Kinds of gripper: two fingers closing on the object, or a suction cup.
KINDS = ("parallel_jaw", "suction")


@dataclass(frozen=True)
class GripperSpec:
    """A parallel-jaw gripper as grasp files and the sampler see it.

    Attributes:
        name: Registry name (``candidates.gripper``).
        description: One line for humans.
        max_width: Largest finger opening [m].
        finger_depth: How far the finger pads reach along the approach, from
            the fingertips back toward the palm [m]; a sampled grasp puts its
            contacts at most this deep.
        base_to_tcp: Distance from the hand's base frame to the fingertip
            midpoint (the robot's grasp frame) along the approach [m].
        kind: ``parallel_jaw`` or ``suction`` (no fingers: ``max_width`` is
            0 and the antipodal sampler refuses it).
        closing_axis: The axis of the hand's base frame along which the
            fingers close (``x`` in the ACRONYM/GraspGen convention); the
            robot's grasp frame closes along its y.
        finger_joints: The hand's finger joints in robot models (exported
            postures; a robot spec that locks them carries this hand).
        hand_frame: The hand's base link in robot models.
        finger_length: From the grasp frame's origin back to the palm along the
            approach [m].
        finger_tip: How far the fingertips reach past the grasp frame's origin [m].
        finger_thickness: Finger size along the closing axis [m].
        finger_width: Finger size across (the grasp frame's x) [m].
        palm_size: Palm box (x, y, z) behind the fingers [m] (the sampler's
            collision check points).
        aliases: Other names grasp files give this gripper (ACRONYM's
            ``gripper/type``, GraspGen's gripper name).
        tool: The gripper as a tool for an arm's flange: its collision and
            visual shapes in its base frame, ``mount`` (base in the flange
            frame), ``tcp`` (= ``to_tool("base")``); ``flange`` is filled in
            when it is mounted (``robot.tool``). None: not given.
        path: The YAML file it was read from.
    """

    name: str
    description: str
    max_width: float
    finger_depth: float
    base_to_tcp: float
    kind: str = "parallel_jaw"
    closing_axis: str = "x"
    finger_joints: tuple[str, ...] = ()
    hand_frame: str = ""
    finger_length: float = 0.037
    finger_tip: float = 0.009
    finger_thickness: float = 0.026
    finger_width: float = 0.021
    palm_size: tuple[float, float, float] = (0.064, 0.208, 0.092)
    aliases: tuple[str, ...] = ()
    tool: ToolSpec | None = None
    path: Path | None = None

    def to_tool(self, convention: str, depth: np.ndarray | float | None = None) -> np.ndarray:
        """The right-hand transform from a file's gripper frame to the robot's grasp frame.

        Args:
            convention: ``base`` or ``center`` (:data:`CONVENTIONS`).
            depth: ``center`` only: how far the fingertips reach past the
                grasp centre along its x [m], scalar or (N,). The grasp frame
                is put ``finger_tip`` behind that point, so that the robot's
                fingertips end where the file's do.

        Returns:
            (4, 4), or (N, 4, 4) for an array ``depth``: ``T_tool = T_file @ to_tool``.
        """
        if convention == "base":
            m = np.eye(4)
            if self.closing_axis == "x":
                # tool z = file z (approach); tool y = file x (closing); tool x = y x z = -file y
                m[:3, :3] = [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
            m[2, 3] = self.base_to_tcp
            return m
        if convention == "center":
            d = np.atleast_1d(np.asarray(0.0 if depth is None else depth, dtype=float))
            m = np.zeros((d.shape[0], 4, 4))
            # tool z = file x (approach); tool y = file y (closing); tool x = -file z
            m[:, :3, :3] = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]
            # the file's fingertips are `depth` past its centre; ours `finger_tip` past the TCP
            m[:, 0, 3] = d - self.finger_tip
            m[:, 3, 3] = 1.0
            return m[0] if depth is None or np.ndim(depth) == 0 else m
        raise choice_error(ConfigError, "gripper frame convention", convention, CONVENTIONS)

    def from_tool(self, convention: str, depth: np.ndarray | float | None = None) -> np.ndarray:
        """The inverse of :meth:`to_tool`: the robot's grasp frame back to the file's gripper frame.

        ``T_file = T_tool @ from_tool``; e.g. to place a gripper's own
        collision mesh (given in its file frame) at a grasp of the table.

        Returns:
            (4, 4), or (N, 4, 4) for an array ``depth``.
        """
        m = self.to_tool(convention, depth)
        inv = np.zeros_like(m)
        rot_t = np.swapaxes(m[..., :3, :3], -1, -2)
        inv[..., :3, :3] = rot_t
        inv[..., :3, 3] = -np.einsum("...ij,...j->...i", rot_t, m[..., :3, 3])
        inv[..., 3, 3] = 1.0
        return inv

    def __repr__(self) -> str:
        return (
            f"GripperSpec({self.name!r}, max_width={self.max_width} m, "
            f"finger_depth={self.finger_depth} m, base_to_tcp={self.base_to_tcp} m)"
        )


#: The gripper a format's dataset was made with, for files that name none. ACRONYM's
#: grasps are all for the Franka hand (``gripper/type: panda``); Contact-GraspNet is
#: trained on ACRONYM; GraspNet-1Billion's grasp-centre rows fit any parallel-jaw hand,
#: and the Franka hand's fingertips place the TCP. GraspGen is not listed: it publishes
#: grasps for several grippers (``franka_panda``, ``robotiq_2f_140``, a suction cup) in
#: one layout, and a file that does not name its gripper needs ``candidates.gripper``.
DATASET_GRIPPERS: dict[str, str] = {
    "acronym": "franka_panda",
    "contact_graspnet": "franka_panda",
    "graspnet": "franka_panda",
}


def registry_dir() -> Any:
    """The folder of the shipped gripper YAML files (``gcm_pipeline/grippers``)."""
    return resources.files("gcm_pipeline") / "grippers"


def shipped_grippers() -> list[str]:
    """Names of the grippers shipped with the package (their YAML files' stems), sorted."""
    return sorted(
        p.name[: -len(".yaml")] for p in registry_dir().iterdir() if p.name.endswith(".yaml")
    )


def is_gripper_path(text: str) -> bool:
    """Whether ``candidates.gripper`` / ``robot.tool`` names a file, not a shipped gripper."""
    return text.endswith((".yaml", ".yml")) or "/" in text or os.sep in text


def check_gripper_ref(text: str) -> str:
    """A shipped gripper's name or a YAML path, as the config takes it.

    Raises:
        ValueError: Neither (the message lists the shipped grippers).
    """
    if not is_gripper_path(text) and text not in shipped_grippers():
        raise ValueError(
            unknown_choice("gripper", text, shipped_grippers())
            + " (or a path to a gripper YAML file)"
        )
    return text


def find_gripper(name: str, registry: Mapping[str, GripperSpec]) -> GripperSpec | None:
    """The gripper a file calls ``name`` (a registry name or an alias, any case), or None."""
    key = name.strip().lower()
    for spec in registry.values():
        if key == spec.name or key in spec.aliases:
            return spec
    return None


@dataclass(frozen=True)
class GripperChoice:
    """How a grasp file's gripper frame is mapped onto the robot's grasp frame.

    Attributes:
        format: The file's format.
        gripper: The registry gripper used, or None (``grasp_to_tool``).
        chosen_by: ``config`` (``candidates.gripper``), ``robot_tool`` (``robot.tool``,
            for a file that names no gripper), ``file`` (the gripper
            the file names), ``dataset`` (the format's dataset gripper,
            :data:`DATASET_GRIPPERS`) or ``grasp_to_tool``.
        file_gripper: The gripper as the file names it, if it does.
    """

    format: str
    gripper: str | None
    chosen_by: str
    file_gripper: str | None = None

    def describe(self) -> str:
        """One line for the run's output."""
        named = f", the file names {self.file_gripper!r}" if self.file_gripper else ""
        if self.gripper is None:
            return f"{self.format} poses mapped by candidates.grasp_to_tool{named}"
        why = {
            "config": "candidates.gripper",
            "file": "named by the file",
            "dataset": f"the {self.format} dataset's gripper",
            "robot_tool": "the robot's tool, robot.tool: the file names no gripper",
        }[self.chosen_by]
        return f"{self.gripper} ({why}{named if self.chosen_by != 'file' else ''})"

    def as_dict(self) -> dict[str, Any]:
        """``summary.json``'s ``grasp_frame``."""
        return {
            "format": self.format,
            "gripper": self.gripper,
            "chosen_by": self.chosen_by,
            "file_gripper": self.file_gripper,
        }


def choose_gripper(
    path: object,
    fmt: str,
    configured: GripperSpec | None,
    mapped: bool,
    file_gripper: str | None,
    registry: Mapping[str, GripperSpec],
    tool: GripperSpec | None = None,
) -> GripperChoice:
    """The gripper whose frame the file's poses are in (see the module docstring).

    Args:
        path: The file (for messages).
        fmt: Its format (one of :data:`~gcm_pipeline.sources.files.GRIPPER_FORMATS`).
        configured: ``candidates.gripper``, read.
        mapped: Whether ``candidates.grasp_to_tool`` is given.
        file_gripper: The gripper the file names, if any.
        registry: The shipped grippers by name (a file's gripper is looked up here).
        tool: The robot's tool (``robot.tool``), read: the gripper of a file that
            names none and whose format has no dataset gripper.

    Raises:
        InputError: The file names a gripper the registry does not know, or
            names none and its format has no dataset gripper (the message
            lists the known grippers and ``grasp_to_tool``; attributes ``key``,
            ``value``: the file's gripper, ``choices``).
    """
    if mapped:
        return GripperChoice(fmt, None, "grasp_to_tool", file_gripper)
    known = ", ".join(sorted(registry))
    if configured is not None:
        spec = configured
        if file_gripper is not None and find_gripper(file_gripper, registry) is not spec:
            log.warning(
                "%s: grasps made for gripper %r are mapped onto %r (candidates.gripper)",
                path,
                file_gripper,
                spec.name,
            )
        return GripperChoice(fmt, spec.name, "config", file_gripper)
    if file_gripper is not None:
        found = find_gripper(file_gripper, registry)
        if found is None:
            raise _refused(
                f"{path}: its grasps are for gripper {file_gripper!r}, which the gripper "
                f"registry does not know (known: {known}); give candidates.grasp_to_tool "
                "(its gripper frame -> the robot's grasp frame), or candidates.gripper to "
                "map it as a known one",
                path,
                file_gripper,
                registry,
            )
        return GripperChoice(fmt, found.name, "file", file_gripper)
    if fmt in DATASET_GRIPPERS:
        return GripperChoice(fmt, DATASET_GRIPPERS[fmt], "dataset")
    if tool is not None:  # grasps made for the hand the robot carries
        return GripperChoice(fmt, tool.name, "robot_tool")
    raise _refused(
        f"{path}: this {fmt} file does not name its gripper, and {fmt} grasps are made for "
        "several grippers whose frames differ; set candidates.gripper (one of: "
        f"{known}), robot.tool (the hand the robot carries, if these are its grasps) or "
        "candidates.grasp_to_tool",
        path,
        None,
        registry,
    )


def _refused(
    message: str, path: object, value: str | None, registry: Mapping[str, GripperSpec]
) -> InputError:
    return InputError(
        message,
        path=path,  # type: ignore[arg-type]
        key="candidates.gripper",
        value=value,
        choices=(*sorted(registry), "grasp_to_tool"),
    )
