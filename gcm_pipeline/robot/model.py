"""Robot specs loaded into reduced Pinocchio models.

A :class:`RobotSpec` is the plain, validated content of a robot spec file
(``gcm_pipeline/robot/specs/<name>.yaml``); :mod:`gcm_pipeline.config.robot_spec`
reads and validates those files (``load_spec``, ``load_robot``). A
:class:`Robot` is built from a spec: the model it names (an
example-robot-data loader, a ``robot_descriptions`` module or a URDF), reduced
to the arm's joints, with limits, home and the grasp frame. Where the model's
files come from is :mod:`~gcm_pipeline.robot.model_files`; the locked joints,
ranges and home of a spec, :mod:`~gcm_pipeline.robot.joints`. Another arm of
example-robot-data is a new YAML file, not new code. Poses are expressed in the
model's root frame (``universe``), called the *base frame*.

A user's URDF is read by :mod:`gcm_pipeline.robot.urdf`: continuous joints become
revolute over [-2π, 2π] (or the ``joint_limits`` range), meshes resolve against
``package_dirs`` then the URDF's folder and its parents, and frames resolve by name
and type (a link and a joint of one name mean the link).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from gcm_pipeline.errors import InputError, RobotSpecError, choice_error, clip
from gcm_pipeline.geometry.meshes import MeshReadError, read_mesh
from gcm_pipeline.robot.chain import KinematicChain
from gcm_pipeline.robot.hand import (
    checked_drop_collision,
    checked_hand_links,
    hand_links,
    urdf_links,
    wrist_link,
)
from gcm_pipeline.robot.joints import home_configuration, joint_ranges, locked_joints
from gcm_pipeline.robot.model_files import check_srdf, model_files
from gcm_pipeline.robot.tool import ToolSpec, shape_geometry
from gcm_pipeline.robot.urdf import (
    PreparedUrdf,
    build_model,
    captured_output,
    prepare_urdf,
    resolve_frame,
)

__all__ = ["Robot", "RobotSpec", "as_robot"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RobotSpec:
    """A validated robot spec (see the module docstring for the YAML keys).

    Attributes:
        name: Robot name.
        description: Free text.
        path: The YAML file the spec was read from (None if built in code).
        example_robot_data: Loader name in ``example_robot_data`` or None.
        robot_descriptions: Module name in ``robot_descriptions`` or None.
        urdf: URDF path or None (then one of the two above is set).
        srdf: SRDF path or None.
        package_dirs: Directories resolving ``package://`` URIs.
        grasp_frame: Name of the frame that IK targets.
        locked_joints: Joint name -> locked value [rad or m].
        home: Joint name -> home value [rad] (empty: middle of the limits).
        limit_margin: Margin by which every revolute joint's range shrinks per side
            [rad] (default 0.1: a controller refuses or cannot hold a joint at its
            limit; see the robots page of the docs; 0 on request). Prismatic
            joints and a continuous joint's default two turns keep their range.
        joint_limits: Joint name -> (lower, upper) [rad], intersected with the model's.
        tool: A tool mounted on a flange frame (:mod:`gcm_pipeline.robot.tool`) or None;
            with a tool, ``grasp_frame`` names the TCP frame the tool adds.
        hand_links: The links of the hand, which may touch the object at a grasp
            (MoveIt's end-effector group); None: found from the model
            (:mod:`gcm_pipeline.robot.hand`).
        drop_collision: Links whose collision geometry is not loaded (checked
            against nothing; still drawn).
    """

    name: str
    grasp_frame: str
    description: str = ""
    path: Path | None = None
    example_robot_data: str | None = None
    robot_descriptions: str | None = None
    urdf: Path | None = None
    srdf: Path | None = None
    package_dirs: tuple[Path, ...] = ()
    locked_joints: Mapping[str, float] = field(default_factory=dict)
    home: Mapping[str, float] | tuple[float, ...] = field(default_factory=dict)
    limit_margin: float = 0.1
    joint_limits: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    tool: ToolSpec | None = None
    hand_links: tuple[str, ...] | None = None
    drop_collision: tuple[str, ...] = ()


def _tool_shapes(spec: RobotSpec, hand_links: list[str]) -> dict[str, list[tuple[Any, Any, Any]]]:
    """The tool's collision and visual shapes with their geometry and pose (meshes read now).

    ``hand_links``: the model's hand links with collision geometry (no warning for a
    TCP-only tool on a hand the model has).
    """
    shapes_of: dict[str, list[tuple[Any, Any, Any]]] = {}
    if spec.tool is None:
        return shapes_of
    tool, where = spec.tool, f"robot spec {str(spec.path)!r}: tool"
    if not tool.collision and not hand_links:
        log.warning(
            "robot %r: the tool %r is a TCP only (no collision shapes): the hand is "
            "not collision-checked, only the arm's links are",
            spec.name,
            tool.name,
        )
    for kind in ("collision", "visual"):
        shapes = tool.collision if kind == "collision" else tool.visual
        shapes_of[kind] = [
            (s, shape_geometry(s, f"{where}.{kind}[{i}]"), tool.shape_pose(s))
            for i, s in enumerate(shapes)
        ]
    return shapes_of


def _check_mimic(spec: RobotSpec, prepared: PreparedUrdf, locked: Mapping[str, float]) -> None:
    """Refuse a mimic joint left free, or locked while the joint it follows moves.

    Pinocchio (without ``mimic=True``) reads a mimic joint as an independent joint:
    free, the IK would move it on its own; locked with a free leader, it would not
    follow. A mimic joint of a locked joint is locked where it follows
    (:func:`~gcm_pipeline.robot.joints.mimic_locks`).
    """
    for joint, mimic in prepared.mimic.items():
        leader = mimic.leader
        leader_free = leader in prepared.moving and leader not in locked
        if joint in locked and leader_free:
            raise RobotSpecError(
                f"robot {spec.name!r}: joint {joint!r} is locked but mimics {leader!r}, which "
                f"is free: it would not follow; lock {leader!r} instead (the joints that "
                "mimic it follow)"
            )
        if joint in locked or joint not in prepared.moving:
            continue
        lock = leader if leader_free else joint
        raise RobotSpecError(
            f"robot {spec.name!r}: joint {joint!r} mimics {leader!r} in the URDF; mimic "
            f"joints are not supported as free joints: lock {lock!r} (locked_joints: "
            f"{{{lock}: value}}; the joints that mimic it follow)"
        )


def _check_all_joints_move_the_grasp_frame(robot: Robot) -> None:
    """Refuse free joints that do not move the grasp frame (a head, wheels, fingers).

    The IK cannot decide them (their Jacobian columns are zero): each would keep
    whatever value its seed had (home, a library or random configuration), so
    collisions would be checked with, and solutions report, arbitrary postures of
    them. The message lists them at their home values, ready to lock.
    """
    on_chain = {int(j) for j in robot.chain.joint_ids}
    model = robot.model
    idle = [j for j in range(1, model.njoints) if j not in on_chain]
    if not idle:
        return
    names = [str(model.names[j]) for j in idle]
    values = ", ".join(
        f"{n}: {float(robot.home[model.joints[j].idx_q]):.4g}"
        for n, j in zip(names, idle, strict=True)
    )
    raise RobotSpecError(
        f"robot {robot.name!r}: {len(idle)} free joint(s) do not move the grasp frame "
        f"{robot.grasp_frame!r}: {', '.join(names)}; the IK cannot set them, so every "
        f"solution would hold them at arbitrary values: lock them "
        f"(locked_joints: {{{values}}})"
    )


class Robot:
    """A robot arm: reduced Pinocchio model, limits, home and grasp frame.

    Build it from a :class:`RobotSpec` (by name: :func:`gcm_pipeline.config.robot_spec.load_robot`).
    All poses are in the base frame (the model's root frame); the grasp-frame
    Jacobian is expressed in ``pin.LOCAL_WORLD_ALIGNED``: rows ``[v; omega]`` are
    the linear velocity of the grasp-frame origin and the angular velocity, both
    in base-frame axes.

    Attributes:
        spec: The spec it was built from.
        name: Robot name.
        model: Reduced Pinocchio model (arm joints only).
        data: A ``pin.Data`` of ``model`` (not thread-safe; make your own for threads).
        full_model: The unreduced model as read from the URDF.
        nq: Number of arm joints.
        joint_names: Arm joint names, in configuration order.
        lower: Lower joint limits (nq,) [rad], after margin and overrides.
        upper: Upper joint limits (nq,) [rad].
        home: Home configuration (nq,) [rad].
        grasp_frame: Grasp frame name.
        grasp_frame_id: Its index in ``model.frames``.
        locked_q: Full-model configuration used for the reduction (locked values).
        urdf_path: URDF file.
        urdf_xml: The URDF as the model was built from it (continuous joints
            revolute, mesh paths absolute; see :mod:`gcm_pipeline.robot.urdf`).
        urdf: The prepared URDF (root link, robot name, meshes, continuous joints).
        continuous_joints: Arm joints that are continuous in the URDF, with the
            range they were given [rad].
        srdf_path: SRDF file or None.
        package_dirs: Directories that resolve the URDF's ``package://`` URIs.
        mesh_dir: Directory of the robot's description (meshes under it).
        shoulder: Origin of the first joint in the base frame (3,) [m].
        max_reach: Largest distance from ``shoulder`` to the grasp frame over
            configurations inside the limits [m], maximised numerically (plus a
            2 mm safety margin); the IK's ``out_of_reach`` pre-filter.
        reach_bound: Sum of the link offsets from the shoulder to the grasp frame,
            a rigorous upper bound of ``max_reach`` [m].
        chain: Vectorised kinematics of the grasp frame.
        locked_values: Every locked joint -> its value [rad or m]: the spec's, and
            the mimic joints that follow them at ``multiplier * value + offset``.
        hand_links: The hand's links (:mod:`gcm_pipeline.robot.hand`): the spec's
            ``hand_links``, else found from the model; they may touch the object at a
            grasp by the contact tolerance.
        model_hand_links: Those of them with collision geometry, in URDF order; by
            default without the link the last free joint moves (a bare wrist is no
            hand).
        dropped_links: The spec's ``drop_collision``: links without collision geometry.
        cache: Per-robot caches of the IK backends (seed library, MuJoCo model).
    """

    def __init__(self, spec: RobotSpec) -> None:
        self.spec = spec
        self.cache: dict[Any, Any] = {}
        self.name = spec.name
        urdf, srdf, package_dirs = model_files(spec)
        if not urdf.is_file():
            raise RobotSpecError(f"robot {spec.name!r}: URDF {str(urdf)!r} does not exist")
        self.urdf_path = urdf
        self.srdf_path = srdf
        self.mesh_dir = urdf.parent.parent
        prepared = prepare_urdf(urdf, package_dirs, spec.joint_limits)
        self.urdf: PreparedUrdf = prepared
        self.urdf_xml = prepared.xml
        self.package_dirs = prepared.package_dirs
        full = build_model(prepared)
        # reduced without the tool's frame, which is then added to it: buildReducedModel
        # finds a frame's parent frame by name alone, and a flange named by a link and a
        # joint alike (Sawyer's right_hand) would make it raise (the tool's frame is the
        # last, so the frames before it have the same indices in both)
        bare = self._bare_model = full.copy()
        if spec.tool is not None:
            _add_tool_frame(spec, full)
        self.full_model = full
        if srdf is not None:
            check_srdf(spec.name, srdf)
        locked_q, locked_ids, locked_values = locked_joints(spec, full, prepared.mimic)
        _check_mimic(spec, prepared, locked_values)
        self.locked_q = locked_q
        #: every locked joint's value: the spec's and the mimic joints that follow them
        self.locked_values = locked_values
        if locked_ids:
            model = pin.buildReducedModel(bare, locked_ids, locked_q)
            if spec.tool is not None:
                _add_tool_frame(spec, model)
        else:
            model = full.copy()
        self.model = model
        self.data = model.createData()
        self.nq = int(model.nq)
        self.joint_names = tuple(model.names[i] for i in range(1, model.njoints))
        where = f"robot {spec.name!r}"
        self.grasp_frame = spec.grasp_frame
        self.grasp_frame_id = resolve_frame(model, spec.grasp_frame, "grasp frame", where)
        if model.frames[self.grasp_frame_id].parentJoint == 0:
            # on the base: the IK can move nothing, every grasp would read "out of reach"
            raise RobotSpecError(
                f"{where}: no free joint moves the grasp frame {spec.grasp_frame!r} (it is "
                "fixed to the base, or every joint between them is locked): free the joints "
                "of its arm or name a frame on the arm"
            )
        #: the grasp frame's index in ``full_model``
        self.full_grasp_frame_id = resolve_frame(full, spec.grasp_frame, "grasp frame", where)
        self.continuous_joints = {
            j: r for j, r in prepared.continuous.items() if j in self.joint_names
        }
        self.chain = KinematicChain(model, self.grasp_frame_id)

        lower, upper = joint_ranges(spec, model, prepared, self.continuous_joints, urdf)
        lower.setflags(write=False)
        upper.setflags(write=False)
        self.lower = lower
        self.upper = upper

        home = home_configuration(spec, self.joint_names, lower, upper)
        home.setflags(write=False)
        self.home = home
        _check_all_joints_move_the_grasp_frame(self)
        links, with_collision, massive = urdf_links(prepared.xml)
        self.dropped_links = checked_drop_collision(
            spec.drop_collision, links, with_collision, where
        )
        shaped = {n for n in with_collision if n not in self.dropped_links}
        if spec.hand_links is None:
            tool = spec.tool
            beside = tool is None or not tool.collision
            hand = hand_links(full, self.full_grasp_frame_id, self.joint_names, beside, massive)
            # a bare wrist link is no hand of the model (the TCP-only tool's warning)
            shaped.discard(wrist_link(full, self.full_grasp_frame_id, self.joint_names))
        else:
            hand = checked_hand_links(spec.hand_links, model, self.grasp_frame_id, links, where)
        #: the hand's links (BODY frames), which may touch the object at a grasp
        self.hand_links = hand
        #: the hand's links with collision geometry (a bare wrist link aside), in URDF order
        self.model_hand_links = [n for n in links if n in hand and n in shaped]
        self._tool_shapes: dict[str, list[tuple[Any, Any, Any]]] = {}
        if spec.tool is not None:  # read the meshes now: a bad one fails before any work
            self._tool_shapes = _tool_shapes(spec, self.model_hand_links)
        self.shoulder = self.chain.root_origin.copy()
        self.reach_bound = float(self.chain.link_lengths().sum())
        self.max_reach = min(self.reach_bound, self._maximise_reach() + 2e-3)

    def _maximise_reach(self, samples: int = 20000, starts: int = 32, steps: int = 300) -> float:
        """Numerical maximum of |p(q) - shoulder| inside the limits [m].

        Projected gradient ascent from the farthest of ``samples`` random
        configurations (fixed seed, deterministic).
        """
        q = self.random_configurations(samples, np.random.default_rng([7, 0x5EAC]))
        d = np.linalg.norm(self.chain.pose(q)[1] - self.shoulder, axis=1)
        best = float(d.max())
        q = q[np.argsort(-d)[:starts]]
        step = 0.5
        for _ in range(steps):
            _, p, jac = self.chain.pose_jacobian(q)
            r = p - self.shoulder
            dist = np.linalg.norm(r, axis=1)
            best = max(best, float(dist.max()))
            grad = np.einsum("ni,nij->nj", r / dist[:, None], jac[:, :3])
            q = np.clip(q + step * grad, self.lower, self.upper)
        dist = np.linalg.norm(self.chain.pose(q)[1] - self.shoulder, axis=1)
        return max(best, float(dist.max()))

    # -- kinematics ---------------------------------------------------------------------

    def as_configurations(self, q: Any) -> np.ndarray:
        """Configurations as a float array (N, nq); one (nq,) becomes (1, nq).

        Raises:
            InputError: Any other shape.
        """
        arr = np.asarray(q, dtype=float)
        if arr.ndim == 1:
            arr = arr[None]
        if arr.ndim != 2 or arr.shape[1] != self.nq:
            raise InputError(f"q must have shape (N, {self.nq}), got {np.shape(q)}")
        return arr

    def fk(self, q: Any) -> np.ndarray:
        """Grasp-frame poses in the base frame.

        Args:
            q: Configurations (N, nq) or (nq,) [rad].

        Returns:
            Homogeneous transforms (N, 4, 4) [m].
        """
        rot, pos = self.chain.pose(self.as_configurations(q))
        out = np.zeros((rot.shape[0], 4, 4))
        out[:, :3, :3] = rot
        out[:, :3, 3] = pos
        out[:, 3, 3] = 1.0
        return out

    def jacobian(self, q: Any) -> np.ndarray:
        """Grasp-frame Jacobians, ``pin.LOCAL_WORLD_ALIGNED``.

        Args:
            q: Configurations (N, nq) or (nq,) [rad].

        Returns:
            Jacobians (N, 6, nq); rows ``[v; omega]`` in base-frame axes
            ([m/rad] and [rad/rad]).
        """
        return self.chain.pose_jacobian(self.as_configurations(q))[2]

    def fk_pinocchio(self, q: Any) -> np.ndarray:
        """Grasp-frame poses computed by Pinocchio itself, one configuration at a time.

        Slower than :meth:`fk` (a Python loop); used to verify IK solutions.

        Args:
            q: Configurations (N, nq) or (nq,) [rad].

        Returns:
            Homogeneous transforms (N, 4, 4) [m].
        """
        qs = self.as_configurations(q)
        out = np.empty((qs.shape[0], 4, 4))
        # a Data of this call's own: threads sharing the robot must not overwrite each other's
        model, data, fid = self.model, self.model.createData(), self.grasp_frame_id
        fk, frame = pin.forwardKinematics, pin.updateFramePlacement
        for i, qi in enumerate(qs):
            fk(model, data, qi)
            # the placement updateFramePlacement returns: no second lookup in data.oMf
            out[i] = frame(model, data, fid).homogeneous
        return out

    def within_limits(self, q: Any, strict: bool = True) -> np.ndarray:
        """Whether each configuration lies inside the joint limits.

        Args:
            q: Configurations (N, nq) [rad].
            strict: Require ``lower < q < upper`` (else ``<=``).

        Returns:
            (N,) bool.
        """
        qs = self.as_configurations(q)
        if strict:
            return np.all((qs > self.lower) & (qs < self.upper), axis=1)
        return np.all((qs >= self.lower) & (qs <= self.upper), axis=1)

    def random_configurations(self, n: int, seed: int | np.random.Generator = 0) -> np.ndarray:
        """Uniformly random configurations inside the limits (n, nq) [rad]."""
        rng = np.random.default_rng(seed)
        return self.lower + rng.random((n, self.nq)) * (self.upper - self.lower)

    def build_geometry(self, kind: str = "collision") -> pin.GeometryModel:
        """Collision or visual geometry of the reduced model.

        Args:
            kind: ``"collision"`` or ``"visual"``.

        Returns:
            A ``pin.GeometryModel`` whose objects are attached to ``model``'s joints.
        """
        kinds = {"collision": pin.GeometryType.COLLISION, "visual": pin.GeometryType.VISUAL}
        if kind not in kinds:
            raise choice_error(RobotSpecError, "geometry kind", kind, kinds)
        # loaded from the URDF and its meshes once per robot; each caller gets a copy
        # it may extend (a placement study builds many collision worlds on one robot)
        cached = self.cache.get(("geometry", kind))
        if cached is None:
            cached = self.cache[("geometry", kind)] = self._load_geometry(kind, kinds[kind])
        return cached.copy()

    def _load_geometry(self, kind: str, geometry_type: Any) -> pin.GeometryModel:
        try:
            with captured_output():
                geom = pin.buildGeomFromUrdfString(
                    self.full_model,
                    self.urdf_xml,
                    geometry_type,
                    package_dirs=[str(p) for p in self.package_dirs],
                )
        except Exception as exc:  # pinocchio raises ValueError/RuntimeError
            raise self._geometry_error(kind, exc) from None
        if kind == "collision" and self.dropped_links:
            fm = self.full_model
            for go in list(geom.geometryObjects):
                if fm.frames[go.parentFrame].name in self.dropped_links:
                    geom.removeGeometryObject(go.name)
        locked = [
            self.full_model.getJointId(j)
            for j in self.locked_values
            if self.full_model.existJointName(j)
        ]
        if locked:
            _, geom = pin.buildReducedModel(self._bare_model, geom, locked, self.locked_q)
        if self.spec.tool is not None:
            self._add_tool_geometry(geom, kind)
        return geom

    def _geometry_error(self, kind: str, exc: Exception) -> RobotSpecError:
        """A one-line error naming the link and the mesh file that did not load."""
        where = f"robot {self.name!r}: URDF {str(self.urdf_path)!r}"
        for ref in self.urdf.meshes:
            if ref.kind != kind:
                continue
            try:
                read_mesh(ref.path)
            except MeshReadError as bad:
                return RobotSpecError(f"{where}: link {ref.link!r}, {kind} mesh: {bad}")
        lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
        useful = [
            ln for ln in lines if not ln.startswith(("From file:", "in function:", "at line:"))
        ]
        return RobotSpecError(
            f"{where}: cannot load the {kind} geometry: "
            f"{clip('; '.join(useful) or type(exc).__name__, 300)}"
        )

    def tool_tcp_link(self) -> tuple[str, np.ndarray]:
        """The URDF link that carries the tool's TCP frame and the frame's pose in it (4, 4).

        The link is the flange frame's nearest body (link) frame; for a tool only.
        """
        fm = self.full_model
        fid = self.full_grasp_frame_id
        k = int(fm.frames[fid].parentFrame)
        while fm.frames[k].type != pin.FrameType.BODY and k > 0:
            k = int(fm.frames[k].parentFrame)
        body = fm.frames[k]
        rel = np.linalg.inv(body.placement.homogeneous) @ fm.frames[fid].placement.homogeneous
        return body.name, rel

    def _add_tool_geometry(self, geom: pin.GeometryModel, kind: str) -> None:
        """Append the tool's shapes, named ``tool/<name>``, on the flange's joint."""
        tool = self.spec.tool
        assert tool is not None
        fid = resolve_frame(self.model, tool.flange, "tool.flange", f"robot {self.name!r}")
        frame = self.model.frames[fid]
        flange = frame.placement.homogeneous @ tool.mount
        for shape, geometry, pose in self._tool_shapes[kind]:
            m = flange @ pose
            placement = pin.SE3(np.ascontiguousarray(m[:3, :3]), np.ascontiguousarray(m[:3, 3]))
            obj = pin.GeometryObject(
                f"tool/{shape.name}", int(frame.parentJoint), int(fid), placement, geometry
            )
            if shape.mesh is not None:
                obj.meshPath = str(shape.mesh)
                obj.meshScale = np.asarray(shape.scale, dtype=float)
            obj.meshColor = np.asarray(shape.color or tool.color, dtype=float)
            obj.overrideMaterial = True
            geom.addGeometryObject(obj)

    def __repr__(self) -> str:
        return (
            f"Robot({self.name!r}, nq={self.nq}, grasp_frame={self.grasp_frame!r}, "
            f"joints={list(self.joint_names)}, "
            f"lower={np.round(self.lower, 4).tolist()}, upper={np.round(self.upper, 4).tolist()}, "
            f"max_reach={self.max_reach:.3f} m)"
        )

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        """Pickle as the spec it came from (rebuilt on unpickling)."""
        return (Robot, (self.spec,))


def _add_tool_frame(spec: RobotSpec, full: pin.Model) -> None:
    """Add the tool's TCP frame (named ``spec.grasp_frame``) to the unreduced model."""
    tool = spec.tool
    assert tool is not None
    fid = resolve_frame(full, tool.flange, "tool.flange", f"robot {spec.name!r}")
    if full.existFrame(spec.grasp_frame):
        raise RobotSpecError(
            f"robot {spec.name!r}: grasp_frame {spec.grasp_frame!r} already exists in the model; "
            "with a tool, grasp_frame names the new TCP frame the tool adds (e.g. tool_tcp)"
        )
    frame = full.frames[fid]
    m = frame.placement.homogeneous @ tool.mount @ tool.tcp
    placement = pin.SE3(np.ascontiguousarray(m[:3, :3]), np.ascontiguousarray(m[:3, 3]))
    full.addFrame(
        pin.Frame(
            spec.grasp_frame, int(frame.parentJoint), int(fid), placement, pin.FrameType.OP_FRAME
        )
    )


def as_robot(robot: Robot | RobotSpec) -> Robot:
    """``robot`` itself, or the :class:`Robot` built from a spec.

    A robot by name or spec file is :func:`gcm_pipeline.config.robot_spec.load_robot`'s.

    Raises:
        InputError: Neither a Robot nor a RobotSpec.
    """
    if isinstance(robot, Robot):
        return robot
    if isinstance(robot, RobotSpec):
        return Robot(robot)
    raise InputError(
        f"robot must be a Robot or a RobotSpec (gcm_pipeline.load_robot(name or spec file) "
        f"makes one), got {clip(robot)}"
    )
