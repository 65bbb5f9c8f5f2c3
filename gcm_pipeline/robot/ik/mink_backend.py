"""Second IK backend: mink's differential IK on a MuJoCo model of the same URDF.

This is the only module that imports ``mink`` and ``mujoco``, on first use
(:func:`_libraries`): importing the package does not load them. The MuJoCo model
is compiled from the robot's example-robot-data URDF: the ``<robot>`` element
gets ``<mujoco><compiler fusestatic="false" .../></mujoco>`` so fixed links such
as ``panda_hand_tcp`` stay bodies, ``package://`` mesh paths become absolute,
visual geometry is dropped (the ``.dae`` meshes do not load; the STL
collision meshes do), and the spec's locked joints become fixed joints at
their locked value. Joint ranges are set to the robot's (possibly tightened)
limits.

Each target is solved on its own: from a seed, iterate ``mink.solve_ik``
(one :class:`mink.FrameTask` on the grasp frame with gain 1, a
:class:`mink.ConfigurationLimit`, QP solver ``daqp``) and integrate the step
until the pose error is within tolerance, trying the same seeds as the
default backend (warm starts, nearest library configurations, home, random)
until one converges. :func:`gcm_pipeline.robot.ik.solve_ik` verifies every
success with Pinocchio's forward kinematics.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from gcm_pipeline.errors import InputError, RobotSpecError, choice_error
from gcm_pipeline.robot.ik.answer import BackendAnswer
from gcm_pipeline.robot.ik.lm import PinocchioIKOptions, rotation_angle
from gcm_pipeline.robot.ik.seeds import restart_seeds, seed_library

__all__ = ["MinkIKOptions", "mujoco_model", "solve"]


def _libraries() -> tuple[Any, Any]:
    """The ``mink`` and ``mujoco`` modules, imported on first use (heavy, optional)."""
    import mink
    import mujoco

    return mink, mujoco


@dataclass(frozen=True)
class MinkIKOptions:
    """Options of the mink backend (keywords of ``solve_ik``).

    Attributes:
        max_iterations: Differential-IK steps per seed.
        library_seeds: Nearest seed-library configurations tried per target.
        random_restarts: Extra random seeds for targets still failing.
        min_solutions: Stop trying seeds for a target once it has this many
            valid converged solutions (the first one is the target's answer).
        home_seed: Try the home configuration after the library seeds.
        damping: Levenberg-Marquardt damping of the QP.
        limit_gain: Gain of :class:`mink.ConfigurationLimit` in (0, 1].
        solver: QP solver name for ``mink.solve_ik``.
        inner_tolerance: Fraction of the tolerances used to stop iterating.
        random_seed: Seed of the library and random restarts.
    """

    max_iterations: int = 40
    library_seeds: int = 8
    random_restarts: int = 8
    min_solutions: int = 1
    home_seed: bool = True
    damping: float = 1e-9
    limit_gain: float = 0.95
    solver: str = "daqp"
    inner_tolerance: float = 0.05
    random_seed: int = 0

    @classmethod
    def from_kwargs(cls, options: dict[str, Any]) -> MinkIKOptions:
        """Build from keyword options; unknown names are an :class:`InputError`."""
        names = cls.__dataclass_fields__
        for key in options:
            if key not in names:
                raise choice_error(InputError, "mink IK option", key, names)
        return cls(**options)


def _urdf_for_mujoco(robot: Any) -> str:
    """URDF text that MuJoCo compiles (see the module docstring)."""
    # the URDF the model was built from: continuous joints revolute, mesh paths absolute
    root = ET.fromstring(robot.urdf_xml)
    for old in root.findall("mujoco"):
        root.remove(old)
    ext = ET.SubElement(root, "mujoco")
    ET.SubElement(ext, "compiler", fusestatic="false", discardvisual="false", strippath="false")
    for link in root.findall("link"):
        for vis in link.findall("visual"):
            link.remove(vis)
    for mesh in root.iter("mesh"):
        fname = mesh.get("filename", "")
        if fname.startswith("package://"):
            rel = fname[len("package://") :]
            for base in robot.package_dirs:
                cand = Path(base) / rel
                if cand.is_file():
                    mesh.set("filename", str(cand))
                    break
            else:
                raise RobotSpecError(f"mesh {fname!r} not found under {robot.package_dirs}")
    for joint in root.findall("joint"):
        name = joint.get("name")
        if name not in robot.locked_values:
            continue
        value = robot.locked_values[name]
        kind = joint.get("type")
        origin = joint.find("origin")
        if origin is None:
            origin = ET.SubElement(joint, "origin", xyz="0 0 0", rpy="0 0 0")
        xyz = np.array([float(v) for v in origin.get("xyz", "0 0 0").split()])
        rot = Rotation.from_euler("xyz", [float(v) for v in origin.get("rpy", "0 0 0").split()])
        axis_el = joint.find("axis")
        axis = np.array(
            [
                float(v)
                for v in (axis_el.get("xyz", "1 0 0") if axis_el is not None else "1 0 0").split()
            ]
        )
        axis /= np.linalg.norm(axis)
        if kind == "prismatic":
            xyz = xyz + rot.apply(axis * value)
        elif kind in ("revolute", "continuous"):
            rot = rot * Rotation.from_rotvec(axis * value)
        joint.set("type", "fixed")
        origin.set("xyz", " ".join(repr(float(v)) for v in xyz))
        origin.set("rpy", " ".join(repr(float(v)) for v in rot.as_euler("xyz")))
        for tag in ("axis", "limit", "mimic", "dynamics", "safety_controller"):
            for el in joint.findall(tag):
                joint.remove(el)
    if robot.spec.tool is not None:  # the tool's TCP frame becomes a body on a fixed joint
        parent, rel = robot.tool_tcp_link()
        joint = ET.SubElement(root, "joint", name=f"{robot.grasp_frame}_joint", type="fixed")
        ET.SubElement(joint, "parent", link=parent)
        ET.SubElement(joint, "child", link=robot.grasp_frame)
        ET.SubElement(
            joint,
            "origin",
            xyz=" ".join(repr(float(v)) for v in rel[:3, 3]),
            rpy=" ".join(repr(float(v)) for v in Rotation.from_matrix(rel[:3, :3]).as_euler("xyz")),
        )
        ET.SubElement(root, "link", name=robot.grasp_frame)
    return ET.tostring(root, encoding="unicode")


def mujoco_model(robot: Any) -> tuple[Any, np.ndarray]:
    """MuJoCo model of the robot (cached) and the qpos index of each arm joint.

    Args:
        robot: The robot.

    Returns:
        ``(model, qpos_index)`` with ``qpos_index`` (nq,) int in ``robot.joint_names`` order.

    Raises:
        RobotSpecError: If MuJoCo cannot compile the URDF or lacks a joint or
            the grasp-frame body.
    """
    cached = robot.cache.get("mujoco_model")
    if cached is not None:
        return cached
    _, mujoco = _libraries()
    try:
        model = mujoco.MjModel.from_xml_string(_urdf_for_mujoco(robot))
    except ValueError as exc:
        raise RobotSpecError(f"MuJoCo cannot compile {str(robot.urdf_path)!r}: {exc}") from exc
    idx = []
    for i, name in enumerate(robot.joint_names):
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid < 0:
            raise RobotSpecError(f"MuJoCo model of {robot.name!r} has no joint {name!r}")
        model.jnt_range[jid] = (robot.lower[i], robot.upper[i])
        model.jnt_limited[jid] = 1
        idx.append(int(model.jnt_qposadr[jid]))
    if model.nq != robot.nq:
        raise RobotSpecError(
            f"MuJoCo model of {robot.name!r} has nq={model.nq}, expected {robot.nq}"
        )
    if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, robot.grasp_frame) < 0:
        raise RobotSpecError(f"MuJoCo model of {robot.name!r} has no body {robot.grasp_frame!r}")
    out = (model, np.array(idx, dtype=int))
    robot.cache["mujoco_model"] = out
    return out


def solve(
    robot: Any,
    targets: np.ndarray,
    *,
    position_tolerance: float,
    orientation_tolerance: float,
    seeds: np.ndarray | None = None,
    validator: Callable[[np.ndarray], np.ndarray] | None = None,
    return_all: bool = False,
    **options: Any,
) -> BackendAnswer:
    """Solve IK target by target with mink (raw, unverified results).

    Args:
        robot: The robot.
        targets: Grasp-frame poses (N, 4, 4) in the base frame.
        position_tolerance: [m].
        orientation_tolerance: [rad].
        seeds: Optional warm starts (N, K, nq) [rad]; NaN rows are skipped.
        validator: Optional ``q (M, nq) -> (M,) str``, '' = valid.
        return_all: Also return every converged candidate.
        **options: :class:`MinkIKOptions` fields.

    Returns:
        The raw answer, as :func:`gcm_pipeline.robot.ik.pinocchio_backend.solve`'s
        (:class:`~gcm_pipeline.robot.ik.backend.IKBackend`).
    """
    opts = MinkIKOptions.from_kwargs(options)
    mink, _ = _libraries()
    model, qidx = mujoco_model(robot)
    n, nq = targets.shape[0], robot.nq
    configuration = mink.Configuration(model)
    task = _frame_task(mink, robot.grasp_frame)
    limits = [mink.ConfigurationLimit(model, gain=opts.limit_gain)]
    tol_p = position_tolerance * opts.inner_tolerance
    tol_r = orientation_tolerance * opts.inner_tolerance
    lib = seed_library(robot, PinocchioIKOptions(random_seed=opts.random_seed))
    k = max(0, opts.library_seeds)
    nearest = (
        lib.nearest(targets[:, :3, :3], targets[:, :3, 3], k) if k and n else np.zeros((n, 0), int)
    )
    restarts = restart_seeds(robot, max(0, opts.random_restarts), opts.random_seed)

    out_q = np.full((n, nq), np.nan)
    success = np.zeros(n, dtype=bool)
    pos_err = np.full(n, np.inf)
    rot_err = np.full(n, np.inf)
    reason = np.full(n, "no_ik", dtype=object)
    all_index: list[int] = []
    all_q: list[np.ndarray] = []
    all_reason: list[str] = []
    qpos = np.zeros(model.nq)
    for i in range(n):
        task.set_target(mink.SE3.from_matrix(targets[i]))
        trot, tpos = targets[i, :3, :3], targets[i, :3, 3]
        n_valid = 0
        given = None if seeds is None else seeds[i]
        for q0 in _seed_list(given, lib.q[nearest[i]], robot.home, opts.home_seed, restarts):
            qpos[qidx] = np.clip(q0, robot.lower, robot.upper)
            configuration.update(qpos)
            pe, re = _descend(mink, configuration, task, limits, robot.grasp_frame, trot, tpos,
                              (tol_p, tol_r), opts)  # fmt: skip
            q = configuration.q[qidx].copy()
            if not success[i] and (
                pe + re / orientation_tolerance * position_tolerance
                < pos_err[i] + rot_err[i] / orientation_tolerance * position_tolerance
            ):
                pos_err[i], rot_err[i] = pe, re
            if not (pe <= tol_p and re <= tol_r):
                continue
            why = "" if validator is None else str(np.asarray(validator(q[None]))[0])
            if return_all:
                all_index.append(i)
                all_q.append(q)
                all_reason.append(why)
            if why:
                if not success[i]:
                    reason[i] = why
                continue
            if not success[i]:
                out_q[i], success[i], reason[i] = q, True, ""
                pos_err[i], rot_err[i] = pe, re
            n_valid += 1
            if n_valid >= opts.min_solutions:
                break
    if not return_all:
        return BackendAnswer(out_q, success, pos_err, rot_err, reason)
    return BackendAnswer(
        out_q,
        success,
        pos_err,
        rot_err,
        reason,
        all_index=np.array(all_index, dtype=int),
        all_q=np.array(all_q).reshape(-1, nq),
        all_reason=np.array(all_reason, dtype=object),
    )


def _frame_task(mink: Any, frame: str) -> Any:
    """The task of the grasp frame (a body) in mink: position and orientation at equal costs."""
    return mink.FrameTask(
        frame_name=frame,
        frame_type="body",
        position_cost=1.0,
        orientation_cost=1.0,
        gain=1.0,
        lm_damping=0.0,
    )


def _descend(
    mink: Any,
    configuration: Any,
    task: Any,
    limits: list[Any],
    frame: str,
    trot: np.ndarray,
    tpos: np.ndarray,
    tolerances: tuple[float, float],
    opts: MinkIKOptions,
) -> tuple[float, float]:
    """Steps of mink from the configuration's q, in place, until the pose is in tolerance.

    At most ``opts.max_iterations`` steps; returns the last pose's position error [m]
    and rotation error [rad] from the target ``(trot, tpos)``.
    """
    tol_p, tol_r = tolerances
    for _ in range(opts.max_iterations + 1):
        pose = configuration.get_transform_frame_to_world(frame, "body")
        mat = pose.as_matrix()
        pe = float(np.linalg.norm(mat[:3, 3] - tpos))
        re = float(rotation_angle((trot.T @ mat[:3, :3])[None])[0])
        if pe <= tol_p and re <= tol_r:
            break
        vel = mink.solve_ik(
            configuration, [task], 1.0, opts.solver, damping=opts.damping, limits=limits
        )
        configuration.integrate_inplace(vel, 1.0)
    return pe, re


def _seed_list(
    given: np.ndarray | None,
    library: np.ndarray,
    home: Any,
    home_seed: bool,
    restarts: np.ndarray,
) -> list[np.ndarray]:
    """One target's seeds in order: finite given ones, library neighbours, home, restarts."""
    cands: list[np.ndarray] = []
    if given is not None:
        cands += [s for s in given if np.all(np.isfinite(s))]
    cands += list(library)
    if home_seed:
        cands.append(np.asarray(home))
    cands += list(restarts)
    return cands
