"""Collision checking of robot configurations against itself, the environment and the object.

The robot's collision meshes come from the same example-robot-data files as its
kinematic model (:meth:`Robot.build_geometry`), reduced with the same locked
joints (the Panda's fingers are locked *open*, as given in the robot spec). The
world is built from the config:

* **environment**: the support table (a box whose top face is at
  ``table.height``; on by default) and the extra ``obstacles`` (box, cylinder,
  sphere, mesh; placed like the object: a cylinder stands on its base along
  its frame's z, boxes and spheres are centred on their frame);
* **object**: the object being grasped (``ObjectConfig``).

Everything is expressed in the robot's base frame (``base_pose`` maps base to
world), so configurations and IK solutions are used as they are.

Pairs that are checked, by kind (the ``reason`` a colliding configuration gets):

``collision_environment``
    every robot link vs every environment obstacle, except the table vs the
    robot's base links standing on it: links attached to the universe or to
    the first joint that touch the table in the home configuration
    (``panda_link0``; ``panda_link1`` is 0.14 m above it and stays checked).
``collision_self``
    all link pairs on different joints, minus the pairs the SRDF disables
    (``pin.removeCollisionPairs``) and adjacent links (parent/child joints).
``collision_object``
    every robot link, the open fingers included, vs the object. The *gripper*
    (the body that carries the grasp frame and every link below it: ``panda_hand``
    and both fingers) may press into the object by ``contact_tolerance`` ``t``
    (a finger pad closing on the surface is a grasp, not a collision):

    * a **primitive** object (cylinder, box, sphere, plane) is eroded exactly
      (radius / half-sizes minus ``t``) and checked against the gripper: the
      gripper collides when one of its points lies deeper than ``t`` inside
      the object. A ``plane`` object (2 mm thick) erodes to nothing, so the
      gripper may touch it;
    * for a **mesh** object each convex collision piece of the gripper is
      eroded by ``t`` instead (:mod:`gcm_pipeline.robot.contact`) and checked
      against the original mesh: the gripper collides when a point of the
      object's surface lies deeper than ``t`` inside one of its pieces. This is
      never more conservative than the geometry, also for walls thinner than
      ``2 t`` (a mug's wall or handle), which an inward offset of the mesh
      cannot represent. A gripper piece that is not convex is checked
      uneroded (a warning says so).

    Arm links (not gripper) are checked against the full object. coal treats
    a mesh as its surface: a link entirely inside a closed mesh object, crossing
    none of its triangles, is not detected.

When a configuration collides in more than one way, the reason is the first of
environment, self, object.

Checking is batched: ``pin.GeometryPool`` objects and
``pin.computeCollisionsInParallel``, which runs forward kinematics, placement
updates and all pairs of a pool in C++ for every configuration, stopping at a
configuration's first collision. One pool holds the environment pairs, one the
object pairs (coal's narrow phase starts with the bounding volumes of each
pair, the BVH root OBBRSS for meshes, so far-away pairs are cheap), and the
self pairs, the costly part, are split into one pool per link: a vectorised
test of the links' bounding spheres (for all configurations at once) decides
which configurations a link's pool has to see at all. Only configurations
still free after a kind are checked for the next kind. :meth:`CollisionChecker.clearance`
bounds every pair's distance from below with a bounding sphere per link (placed
by vectorised forward kinematics for all configurations at once) against the
world shape's box, and runs coal's exact distance only for pairs that can still
be the nearest.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import coal
import numpy as np
import pinocchio as pin

from gcm_pipeline.config import EnvironmentConfig, ObjectConfig, ObstacleConfig, Pose
from gcm_pipeline.errors import ConfigError, InputError, unknown_choice
from gcm_pipeline.robot.chain import KinematicChain
from gcm_pipeline.robot.contact import (
    NotConvexError,
    SolidMesh,
    erode_convex,
    interior_point,
    mesh_arrays,
)
from gcm_pipeline.robot.model import Robot

__all__ = [
    "REASON_ENVIRONMENT",
    "REASON_OBJECT",
    "REASON_SELF",
    "CollisionChecker",
    "WorldShape",
    "as_transform",
    "shape_geometry",
]

REASON_SELF = "collision_self"
REASON_ENVIRONMENT = "collision_environment"
REASON_OBJECT = "collision_object"

_KINDS = ("environment", "self", "object")
_REASONS = {"environment": REASON_ENVIRONMENT, "self": REASON_SELF, "object": REASON_OBJECT}
_ENV_SHAPES = ("box", "cylinder", "sphere", "mesh")
_OBJECT_SHAPES = ("cylinder", "box", "sphere", "plane", "mesh")
_PLANE_THICKNESS = 0.002  # [m] a 'plane' object is a box this thick, centred on its frame


@dataclass(frozen=True)
class WorldShape:
    """A collision shape of the world, placed in the robot's base frame.

    Attributes:
        name: Geometry name (``table``, ``obstacle_<i>`` or the obstacle's name, ``object``).
        geometry: The coal geometry (centred as coal defines it).
        placement: Pose of the geometry's centre in the base frame (4, 4) [m].
        kind: ``"environment"`` or ``"object"``.
    """

    name: str
    geometry: Any
    placement: np.ndarray
    kind: str


def as_transform(pose: Pose | np.ndarray | None) -> np.ndarray:
    """A pose as a (4, 4) homogeneous transform (identity for None).

    Args:
        pose: A config :class:`Pose`, a (4, 4) array or None.

    Returns:
        (4, 4) transform [m].

    Raises:
        InputError: If an array is not (4, 4) or not finite.
    """
    if pose is None:
        return np.eye(4)
    if isinstance(pose, Pose):
        return pose.matrix()
    arr = np.asarray(pose, dtype=float)
    if arr.shape != (4, 4) or not np.all(np.isfinite(arr)):
        raise InputError(f"a pose must be a finite (4, 4) transform, got shape {arr.shape}")
    return arr


def _load_mesh(path: Path | None, scale: float, where: str) -> Any:
    if path is None:
        raise ConfigError(f"{where}: shape 'mesh' needs 'mesh: <path>'")
    p = Path(path).expanduser()
    if not p.is_file():
        raise InputError(f"{where}: mesh file {str(p)!r} does not exist")
    try:
        mesh = coal.MeshLoader().load(str(p), np.full(3, float(scale)))
    except Exception as exc:  # coal raises ValueError with a multi-line message
        first = str(exc).strip().splitlines()
        detail = next((ln for ln in first if ln.startswith("message:")), first[-1] if first else "")
        raise InputError(f"{where}: cannot read mesh file {str(p)!r}: {detail}") from exc
    if mesh.num_tris == 0:
        raise InputError(f"{where}: mesh file {str(p)!r} has no triangles")
    verts = np.asarray(mesh.vertices())
    if not np.isfinite(verts).all():
        i = int(np.flatnonzero(~np.isfinite(verts).all(axis=1))[0])
        raise InputError(f"{where}: mesh file {str(p)!r}: vertex {i} is not finite")
    return mesh


def _positive(where: str, name: str, value: float | None) -> float:
    if value is None or not math.isfinite(value) or value <= 0:
        raise ConfigError(f"{where}: {name} must be a positive number [m], got {value!r}")
    return float(value)


def shape_geometry(
    shape: str,
    dims: Any,
    *,
    mesh: Path | None = None,
    scale: float = 1.0,
    erode: float = 0.0,
    where: str = "shape",
) -> tuple[Any, np.ndarray] | None:
    """Coal geometry of a config shape and the offset of its centre in the shape's frame.

    Conventions (those of ``ObjectConfig``): a cylinder stands on its base with
    its axis along the frame's z (base at z = 0); boxes and spheres are centred
    on the frame origin; a plane is a ``_PLANE_THICKNESS`` thick box centred on
    the frame's xy plane; a mesh is used as its file defines it (times ``scale``).

    Args:
        shape: ``box``, ``cylinder``, ``sphere``, ``plane`` or ``mesh``.
        dims: A :class:`~gcm_pipeline.config.ShapeDims` (``radius``, ``height``, ``size``).
        mesh: Mesh file (shape ``mesh``).
        scale: Mesh scale factor.
        erode: Distance [m] by which a primitive shrinks on every side (0: the shape
            itself). Meshes are not eroded (the gripper is, see
            :mod:`gcm_pipeline.robot.contact`): ``erode > 0`` with a mesh is a ValueError.
        where: Config location used in error messages.

    Returns:
        ``(geometry, centre)`` with ``centre`` (4, 4) the geometry's pose in the
        shape's frame; None when erosion leaves nothing (a part thinner than
        ``2 * erode``).

    Raises:
        ConfigError: Unknown shape, missing or non-positive size.
        InputError: Mesh file missing or unreadable (names the file).
    """
    centre = np.eye(4)
    if shape == "cylinder":
        radius = _positive(where, "dims.radius", dims.radius) - erode
        height = _positive(where, "dims.height", dims.height)
        centre[2, 3] = 0.5 * height
        height -= 2 * erode
        if radius <= 0 or height <= 0:
            return None
        return coal.Cylinder(radius, height), centre
    if shape in ("box", "plane"):
        want = 3 if shape == "box" else 2
        size = tuple(dims.size or ())
        if len(size) != want:
            raise ConfigError(f"{where}: shape {shape!r} needs dims.size with {want} values")
        sizes = [_positive(where, "dims.size", s) for s in size]
        if shape == "plane":
            sizes.append(_PLANE_THICKNESS)
        eroded = [s - 2 * erode for s in sizes]
        if min(eroded) <= 0:
            return None
        return coal.Box(*eroded), centre
    if shape == "sphere":
        radius = _positive(where, "dims.radius", dims.radius) - erode
        if radius <= 0:
            return None
        return coal.Sphere(radius), centre
    if shape == "mesh":
        if erode > 0:
            raise ValueError(
                "a mesh is not eroded: the gripper's pieces are (gcm_pipeline.robot.contact)"
            )
        _positive(where, "scale", scale)
        return _load_mesh(mesh, scale, where), centre
    raise ConfigError(f"{where}: " + unknown_choice("shape", shape, _OBJECT_SHAPES))


def _se3(m: np.ndarray) -> pin.SE3:
    return pin.SE3(np.ascontiguousarray(m[:3, :3]), np.ascontiguousarray(m[:3, 3]))


def _obstacle_shape(i: int, obs: ObstacleConfig, base_inv: np.ndarray) -> WorldShape:
    where = f"environment.obstacles[{i}]"
    if obs.shape not in _ENV_SHAPES:
        raise ConfigError(f"{where}: " + unknown_choice("shape", obs.shape, _ENV_SHAPES))
    made = shape_geometry(obs.shape, obs.dims, mesh=obs.mesh, scale=obs.scale, where=where)
    assert made is not None
    geom, centre = made
    return WorldShape(
        name=obs.name or f"obstacle_{i}",
        geometry=geom,
        placement=base_inv @ obs.pose.matrix() @ centre,
        kind="environment",
    )


class CollisionChecker:
    """Batched collision checks and clearance of robot configurations.

    Args:
        robot: The robot (its reduced model and collision geometry).
        environment: Table and obstacles; None means the default config
            (a table at z = 0, self-collision on).
        object_cfg: The object being grasped, or None (no object).
        base_pose: Pose of the robot base in the world (config ``robot.base_pose``),
            a (4, 4) transform or None (identity).
        threads: Threads for the batched checks (``pin.computeCollisionsInParallel``).
        holding: The gripper holds the object (a retreat): its links are not
            checked against the object.

    Raises:
        ConfigError: Unknown shape or non-positive size in the environment or object.
        InputError: A mesh file is missing or unreadable (the message names it).

    Attributes:
        robot: The robot.
        geom_model: ``pin.GeometryModel`` with the robot links and world shapes
            and *every* checked pair active (all kinds); usable with
            ``pin.computeCollisions``.
        pair_kind: Kind of each pair of ``geom_model.collisionPairs`` (P,) str.
        n_robot_geoms: Number of robot geometries (the first ones of ``geom_model``).
        gripper_geoms: Indices of the gripper geometries (checked against the eroded object).
        world: The world shapes in the base frame.
    """

    def __init__(
        self,
        robot: Robot,
        environment: EnvironmentConfig | None = None,
        object_cfg: ObjectConfig | None = None,
        base_pose: Pose | np.ndarray | None = None,
        *,
        threads: int = 1,
        holding: bool = False,
    ) -> None:
        env = EnvironmentConfig() if environment is None else environment
        self.holding = bool(holding)
        self.robot = robot
        self.environment = env
        self.object_cfg = object_cfg
        self.threads = max(1, int(threads))
        self.base_pose = as_transform(base_pose)
        base_inv = np.linalg.inv(self.base_pose)
        tol = float(env.contact_tolerance)
        if not math.isfinite(tol) or tol < 0:
            raise ConfigError(f"environment.contact_tolerance must be >= 0 [m], got {tol!r}")
        self.contact_tolerance = tol

        model = robot.model
        gm = robot.build_geometry("collision")
        self.n_robot_geoms = int(gm.ngeoms)
        robot_ids = list(range(self.n_robot_geoms))
        link_of = [model.frames[g.parentFrame].name for g in gm.geometryObjects]
        joint_of = [int(g.parentJoint) for g in gm.geometryObjects]
        self.link_names = tuple(link_of)
        gripper_links = _gripper_links(robot)
        self.gripper_geoms = tuple(i for i in robot_ids if link_of[i] in gripper_links)

        # --- world shapes (base frame) -------------------------------------------------
        world: list[WorldShape] = []
        if env.table is not None:
            t = env.table
            sx, sy, sz = (_positive("environment.table", "size", s) for s in t.size)
            m = np.eye(4)
            m[:3, 3] = (t.center_xy[0], t.center_xy[1], t.height - 0.5 * sz)
            world.append(WorldShape("table", coal.Box(sx, sy, sz), base_inv @ m, "environment"))
        for i, obs in enumerate(env.obstacles):
            world.append(_obstacle_shape(i, obs, base_inv))
        contact_obj: WorldShape | None = None
        if object_cfg is not None and env.check_object:
            if object_cfg.shape not in _OBJECT_SHAPES:
                raise ConfigError(
                    "object: " + unknown_choice("shape", object_cfg.shape, _OBJECT_SHAPES)
                )
            made = shape_geometry(
                object_cfg.shape,
                object_cfg.dims,
                mesh=object_cfg.mesh,
                scale=object_cfg.scale,
                where="object",
            )
            assert made is not None
            obj_m = base_inv @ object_cfg.pose.matrix()
            world.append(WorldShape("object", made[0], obj_m @ made[1], "object"))
            if object_cfg.shape != "mesh":  # primitives: exact object-side erosion
                eroded = shape_geometry(
                    object_cfg.shape, object_cfg.dims, erode=tol, where="object"
                )
                if eroded is not None:
                    contact_obj = WorldShape(
                        "object_contact", eroded[0], obj_m @ eroded[1], "object"
                    )
        self.world = tuple(world)

        world_ids: dict[str, int] = {}
        for shape in [*world, *([contact_obj] if contact_obj is not None else [])]:
            go = pin.GeometryObject(shape.name, 0, 0, _se3(shape.placement), shape.geometry)
            world_ids[shape.name] = int(gm.addGeometryObject(go))

        # --- pairs by kind -----------------------------------------------------------
        pairs: dict[str, list[tuple[int, int]]] = {k: [] for k in _KINDS}
        if env.self_collision:
            self_gm = robot.build_geometry("collision")
            self_gm.addAllCollisionPairs()
            if robot.srdf_path is not None:
                pin.removeCollisionPairs(model, self_gm, str(robot.srdf_path))
            for cp in self_gm.collisionPairs:
                a, b = int(cp.first), int(cp.second)
                ja, jb = joint_of[a], joint_of[b]
                if ja == jb or model.parents[ja] == jb or model.parents[jb] == ja:
                    continue  # same rigid body or adjacent links
                pairs["self"].append((a, b))
        exempt = self._table_exempt(model, gm, world_ids, joint_of) if env.table else set()
        for shape in world:
            if shape.kind != "environment":
                continue
            w = world_ids[shape.name]
            for i in robot_ids:
                if shape.name == "table" and i in exempt:
                    continue
                pairs["environment"].append((i, w))
        if "object" in world_ids:
            mesh = object_cfg is not None and object_cfg.shape == "mesh"
            eroded_ids = _add_eroded_gripper(gm, self.gripper_geoms, tol) if mesh else {}
            for i in robot_ids:
                if i not in self.gripper_geoms:
                    pairs["object"].append((i, world_ids["object"]))
                elif self.holding:
                    continue  # the gripper holds the object: contact is the point
                elif mesh:  # eroded gripper piece vs the original mesh
                    if eroded_ids[i] is not None:
                        pairs["object"].append((eroded_ids[i], world_ids["object"]))
                elif "object_contact" in world_ids:
                    pairs["object"].append((i, world_ids["object_contact"]))
        self.table_exempt = tuple(sorted(link_of[i] for i in exempt))
        self._init_solid(gm, pairs["object"], world_ids)

        # one geometry model per kind (batched checks) plus one with every pair
        self._kind_models: dict[str, Any] = {}
        self._pools: dict[str, Any] = {}
        for kind in _KINDS:
            if not pairs[kind]:
                continue
            km = gm.copy()
            km.removeAllCollisionPairs()
            for a, b in pairs[kind]:
                km.addCollisionPair(pin.CollisionPair(a, b))
            self._kind_models[kind] = km
            if kind != "self":  # self pairs: sphere-filtered groups, see _init_self_groups
                self._pools[kind] = pin.GeometryPool(model, km, self.threads)
        self._init_spheres(model, gm, joint_of)
        self._init_self_groups(model, gm, pairs["self"])
        full = gm.copy()
        full.removeAllCollisionPairs()
        kinds: list[str] = []
        for kind in _KINDS:
            for a, b in pairs[kind]:
                full.addCollisionPair(pin.CollisionPair(a, b))
                kinds.append(kind)
        self.geom_model = full
        self.pair_kind = np.array(kinds, dtype=object)
        self._data = model.createData()
        self._full_data = pin.GeometryData(full)

        # clearance: robot vs environment, arm links (not gripper) vs the full object;
        # base links (universe, first joint) vs the table are left out: their distance
        # to it does not depend on the configuration and would mask the arm's
        base_links = {i for i in robot_ids if joint_of[i] in (0, 1)}
        dist_pairs = [
            (a, b)
            for a, b in pairs["environment"]
            if not (b == world_ids.get("table") and a in base_links)
        ]
        if "object" in world_ids:
            dist_pairs += [
                (i, world_ids["object"]) for i in robot_ids if i not in self.gripper_geoms
            ]
        self._dist_model: Any = None
        if dist_pairs:
            dm = gm.copy()
            dm.removeAllCollisionPairs()
            for a, b in dist_pairs:
                dm.addCollisionPair(pin.CollisionPair(a, b))
            self._dist_model = dm
            self._dist_data = pin.GeometryData(dm)
            self._init_distance_bounds(dm, dist_pairs)

    # --- construction helpers ---------------------------------------------------------

    def _table_exempt(
        self, model: pin.Model, gm: Any, world_ids: dict[str, int], joint_of: list[int]
    ) -> set[int]:
        """Robot geometries not checked against the table: the base links standing on it.

        Links fixed to the universe or to the first joint that touch the table
        in the home configuration (for the Panda at z = 0: ``panda_link0``).
        """
        exempt: set[int] = set()
        first = [i for i in range(self.n_robot_geoms) if joint_of[i] in (0, 1)]
        if not first:
            return exempt
        probe = gm.copy()
        probe.removeAllCollisionPairs()
        for i in first:
            probe.addCollisionPair(pin.CollisionPair(i, world_ids["table"]))
        pd = pin.GeometryData(probe)
        pin.computeCollisions(model, model.createData(), probe, pd, self.robot.home, False)
        for k, cp in enumerate(probe.collisionPairs):
            if pd.collisionResults[k].isCollision():
                exempt.add(int(cp.first))
        return exempt

    def with_contact_tolerance(self, tolerance: float) -> CollisionChecker:
        """The same world with another finger-contact tolerance [m] (0: no contact allowed)."""
        env = self.environment.model_copy(update={"contact_tolerance": float(tolerance)})
        return CollisionChecker(
            self.robot,
            env,
            self.object_cfg,
            self.base_pose,
            threads=self.threads,
            holding=self.holding,
        )

    def holding_object(self) -> CollisionChecker:
        """The same world while the gripper holds the object: gripper vs object not checked."""
        return CollisionChecker(
            self.robot,
            self.environment,
            self.object_cfg,
            self.base_pose,
            threads=self.threads,
            holding=True,
        )

    def _init_spheres(self, model: pin.Model, gm: Any, joint_of: list[int]) -> None:
        """Bounding sphere of every robot geometry, in its joint's frame.

        The sphere circumscribes the geometry's local AABB. Its centre is
        placed for N configurations at once by :meth:`_sphere_centres`
        (vectorised forward kinematics of each joint).
        """
        centres, radii = [], []
        for i in range(self.n_robot_geoms):
            go = gm.geometryObjects[i]
            go.geometry.computeLocalAABB()
            centres.append(go.placement.act(np.asarray(go.geometry.aabb_center, dtype=float)))
            radii.append(float(go.geometry.aabb_radius))
        self._sph_centre = np.array(centres)
        self._sph_radius = np.array(radii)
        self._sph_joint = np.array(joint_of[: self.n_robot_geoms], dtype=int)
        self._chains: dict[int, KinematicChain] = {}
        for j in sorted(set(self._sph_joint.tolist()) - {0}):
            fid = model.getFrameId(model.names[j], pin.FrameType.JOINT)
            if not model.frames[fid].placement.isIdentity():  # pragma: no cover - URDF joints
                raise RuntimeError(f"joint frame {model.names[j]!r} is not at its joint")
            self._chains[j] = KinematicChain(model, fid)

    def _sphere_centres(self, qs: np.ndarray) -> np.ndarray:
        """Centres (N, G, 3) [m] of the robot geometries' bounding spheres, base frame."""
        return self._place_points(qs, self._sph_joint, self._sph_centre)

    def _place_points(self, qs: np.ndarray, joints: np.ndarray, local: np.ndarray) -> np.ndarray:
        """Points (N, P, 3) [m], base frame, of points ``local`` (P, 3) fixed to ``joints`` (P,)."""
        n = len(qs)
        out = np.broadcast_to(local, (n, *local.shape)).copy()
        for j in sorted(set(joints.tolist()) - {0}):
            cols = np.flatnonzero(joints == j)
            rot, pos = self._chains[j].pose(qs)
            out[:, cols] = pos[:, None, :] + np.einsum("nij,pj->npi", rot, local[cols])
        return out

    def _init_solid(self, gm: Any, pairs: list[tuple[int, int]], world_ids: dict[str, int]) -> None:
        """Inside test of a mesh object for the robot pieces of the object pairs.

        coal checks a mesh object as its triangles; a robot piece (an arm link,
        an eroded gripper piece) that lies wholly inside the closed mesh crosses
        none of them. Such a piece is found by testing one of its points
        (:func:`~gcm_pipeline.robot.contact.interior_point`) against the solid
        (:class:`~gcm_pipeline.robot.contact.SolidMesh`) in :meth:`_inside_object`.
        """
        self._solid: SolidMesh | None = None
        obj = self.object_cfg
        if obj is None or obj.shape != "mesh" or "object" not in world_ids or not pairs:
            return
        go = gm.geometryObjects[world_ids["object"]]
        self._solid = SolidMesh(*mesh_arrays(go.geometry))
        self._solid_from_base = np.linalg.inv(go.placement.homogeneous)
        ids = sorted({a for a, _ in pairs})
        self._solid_names = tuple(gm.geometryObjects[i].name for i in ids)
        self._solid_joint = np.array([int(gm.geometryObjects[i].parentJoint) for i in ids])
        self._solid_local = np.array(
            [
                gm.geometryObjects[i].placement.act(interior_point(gm.geometryObjects[i].geometry))
                for i in ids
            ]
        )

    def _inside_object(self, q: np.ndarray) -> np.ndarray:
        """Whether a robot piece of the object pairs lies inside the mesh object, (M,) bool."""
        if self._solid is None or len(q) == 0:
            return np.zeros(len(q), dtype=bool)
        pts = self._place_points(q, self._solid_joint, self._solid_local)
        m = self._solid_from_base
        local = pts @ m[:3, :3].T + m[:3, 3]
        return self._solid.contains(local.reshape(-1, 3)).reshape(pts.shape[:2]).any(axis=1)

    def _init_distance_bounds(self, dm: Any, pairs: list[tuple[int, int]]) -> None:
        """Axis-aligned boxes (base frame) of the world shape of every distance pair.

        The distance between a robot geometry's bounding sphere and the world
        shape's box is a lower bound of the pair's distance; :meth:`clearance`
        computes exact distances in increasing order of that bound and stops
        when the next bound exceeds the best distance found.
        """
        lows, highs = [], []
        for _, b in pairs:
            gb = dm.geometryObjects[b]
            gb.geometry.computeLocalAABB()
            box = gb.geometry.aabb_local
            lo, hi = np.asarray(box.min_, dtype=float), np.asarray(box.max_, dtype=float)
            corners = np.array(
                [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
            )
            world = corners @ np.asarray(gb.placement.rotation).T + np.asarray(
                gb.placement.translation
            )
            lows.append(world.min(axis=0))
            highs.append(world.max(axis=0))
        self._dist_robot = np.array([a for a, _ in pairs], dtype=int)
        self._dist_low = np.array(lows)
        self._dist_high = np.array(highs)

    def _lower_bounds(self, qs: np.ndarray) -> np.ndarray:
        """Lower bounds (N, P) of every distance pair's distance [m], vectorised."""
        centre = self._sphere_centres(qs)[:, self._dist_robot]
        gap = np.maximum(np.maximum(self._dist_low - centre, centre - self._dist_high), 0.0)
        return np.linalg.norm(gap, axis=2) - self._sph_radius[self._dist_robot]

    def _init_self_groups(self, model: pin.Model, gm: Any, pairs: list[tuple[int, int]]) -> None:
        """Self pairs grouped by their first geometry, one pool per group.

        :meth:`check` runs a group's pool only on the configurations where the
        bounding spheres of at least one of its pairs overlap (vectorised
        sphere test), so far-apart links (the base vs the hand) cost nothing.
        """
        self._self_a = np.array([a for a, _ in pairs], dtype=int)
        self._self_b = np.array([b for _, b in pairs], dtype=int)
        self._self_groups: list[tuple[np.ndarray, Any]] = []
        for a in sorted(set(self._self_a.tolist())):
            idx = np.flatnonzero(self._self_a == a)
            km = gm.copy()
            km.removeAllCollisionPairs()
            for k in idx:
                km.addCollisionPair(pin.CollisionPair(int(self._self_a[k]), int(self._self_b[k])))
            self._self_groups.append((idx, pin.GeometryPool(model, km, self.threads)))

    def _self_collides(self, q: np.ndarray) -> np.ndarray:
        """Self-collision of configurations (M, nq) -> (M,) bool, sphere-filtered groups."""
        hit = np.zeros(len(q), dtype=bool)
        if not self._self_groups or len(q) == 0:
            return hit
        centre = self._sphere_centres(q)
        gap = np.linalg.norm(centre[:, self._self_a] - centre[:, self._self_b], axis=2)
        near = gap <= self._sph_radius[self._self_a] + self._sph_radius[self._self_b]
        for idx, pool in self._self_groups:
            rows = np.flatnonzero(near[:, idx].any(axis=1) & ~hit)
            if rows.size == 0:
                continue
            qt = np.asfortranarray(q[rows].T)
            res = pin.computeCollisionsInParallel(self.threads, pool, qt, True, False)
            hit[rows] = np.asarray(res, dtype=bool).reshape(rows.size)
        return hit

    # --- queries --------------------------------------------------------------------------

    def _collides(self, kind: str, q: np.ndarray) -> np.ndarray:
        if kind == "self":
            return self._self_collides(q)
        pool = self._pools.get(kind)
        if pool is None or len(q) == 0:
            return np.zeros(len(q), dtype=bool)
        qt = np.asfortranarray(q.T)
        res = pin.computeCollisionsInParallel(self.threads, pool, qt, True, False)
        hit = np.asarray(res, dtype=bool).reshape(len(q))
        if kind == "object" and self._solid is not None:  # pieces wholly inside the mesh
            free = np.flatnonzero(~hit)
            hit[free] = self._inside_object(q[free])
        return hit

    def check(self, q: Any) -> np.ndarray:
        """Collision reason of each configuration.

        Args:
            q: Configurations (N, nq) or (nq,) [rad]. Non-finite rows are skipped
                (reason ``''``); the caller marks them unreachable anyway.

        Returns:
            (N,) str: ``''`` (free), ``'collision_environment'``,
            ``'collision_self'`` or ``'collision_object'`` (first that applies,
            in this order).
        """
        qs = self.robot.as_configurations(q)
        reason = np.full(len(qs), "", dtype=object)
        todo = np.flatnonzero(np.all(np.isfinite(qs), axis=1))
        for kind in _KINDS:
            if len(todo) == 0:
                break
            hit = self._collides(kind, qs[todo])
            reason[todo[hit]] = _REASONS[kind]
            todo = todo[~hit]
        return reason.astype(str) if len(reason) else np.zeros(0, dtype="<U21")

    def in_collision(self, q: Any) -> np.ndarray:
        """Whether each configuration collides (any kind), (N,) bool."""
        return self.check(q) != ""

    def colliding_pairs(self, q: Any) -> list[tuple[str, str, str]]:
        """All colliding pairs of one configuration (for reports and debugging).

        Args:
            q: One configuration (nq,) [rad].

        Returns:
            ``[(geometry_1, geometry_2, kind), ...]``; a robot piece wholly inside a
            mesh object is ``(piece, "object (inside)", "object")``.
        """
        qs = self.robot.as_configurations(q)[0]
        gm, gd = self.geom_model, self._full_data
        pin.computeCollisions(self.robot.model, self._data, gm, gd, qs, False)
        out = []
        if self._solid is not None:
            pts = self._place_points(qs[None], self._solid_joint, self._solid_local)[0]
            m = self._solid_from_base
            inside = self._solid.contains(pts @ m[:3, :3].T + m[:3, 3])
            out += [
                (self._solid_names[k], "object (inside)", "object") for k in np.flatnonzero(inside)
            ]
        for k, cp in enumerate(gm.collisionPairs):
            if gd.collisionResults[k].isCollision():
                out.append(
                    (
                        gm.geometryObjects[cp.first].name,
                        gm.geometryObjects[cp.second].name,
                        str(self.pair_kind[k]),
                    )
                )
        return out

    def clearance(self, q: Any) -> np.ndarray:
        """Minimum distance of the robot to the environment and the object [m].

        Pairs: every robot link vs every environment obstacle, except the base
        links (fixed to the universe or the first joint) vs the table, whose
        distance to it does not change with the configuration (0.14 m for
        ``panda_link1``), and every *arm* link vs the object.
        The gripper (hand and fingers) vs the object is left out: at a grasp it
        touches the object by design. Penetrating pairs give a distance <= 0
        (a penetration, not necessarily the deepest one).

        Exact distances (coal, on the meshes) are computed only for the pairs
        whose bounding-sphere-to-box lower bound is below the best distance
        found so far (see :meth:`_init_distance_bounds`), nearest bound first.

        Args:
            q: Configurations (N, nq) or (nq,) [rad].

        Returns:
            (N,) distances [m]; ``inf`` when there is nothing to measure against,
            NaN for non-finite configurations.
        """
        qs = self.robot.as_configurations(q)
        out = np.full(len(qs), np.inf)
        if self._dist_model is None:
            out[~np.all(np.isfinite(qs), axis=1)] = np.nan
            return out
        finite = np.all(np.isfinite(qs), axis=1)
        out[~finite] = np.nan
        rows = np.flatnonzero(finite)
        if rows.size == 0:
            return out
        model, data = self.robot.model, self._data
        dm, dd = self._dist_model, self._dist_data
        bound = self._lower_bounds(qs[rows])
        order = np.argsort(bound, axis=1)
        for k, n in enumerate(rows):
            pin.updateGeometryPlacements(model, data, dm, dd, qs[n])
            best = np.inf
            lb = bound[k]
            for p in order[k]:
                if lb[p] >= best:
                    break
                d = pin.computeDistance(dm, dd, int(p)).min_distance
                if d < best:
                    best = d
            out[n] = best
        return out

    def __repr__(self) -> str:
        counts = {k: int(np.sum(self.pair_kind == k)) for k in _KINDS}
        world = ", ".join(s.name for s in self.world) or "(none)"
        return (
            f"CollisionChecker(robot={self.robot.name!r}, world=[{world}], pairs={counts}, "
            f"contact_tolerance={self.contact_tolerance}, table_exempt={list(self.table_exempt)})"
        )


def _add_eroded_gripper(
    gm: Any, gripper_geoms: tuple[int, ...], tol: float
) -> dict[int, int | None]:
    """Add each gripper piece eroded by ``tol`` [m] to ``gm`` (same joint, frame, placement).

    Returns:
        Gripper geometry index -> index of its eroded copy (named ``<name>_contact``),
        or None when the piece erodes to nothing. A piece that cannot be eroded
        (not convex) is used uneroded, with a warning.
    """
    out: dict[int, int | None] = {}
    for i in gripper_geoms:
        go = gm.geometryObjects[i]
        if tol == 0:
            out[i] = i
            continue
        try:
            eroded = erode_convex(go.geometry, tol)
        except NotConvexError as exc:
            warnings.warn(
                f"gripper collision piece {go.name!r}: {exc}; checked against the object "
                "without contact tolerance",
                stacklevel=3,
            )
            out[i] = i
            continue
        if eroded is None:
            out[i] = None
            continue
        piece = pin.GeometryObject(
            f"{go.name}_contact", int(go.parentJoint), int(go.parentFrame), go.placement, eroded
        )
        out[i] = int(gm.addGeometryObject(piece))
    return out


def _gripper_links(robot: Robot) -> set[str]:
    """Links of the gripper: the body carrying the grasp frame and all links below it.

    Walks the *full* (unreduced) model's frame tree: the grasp frame's nearest
    BODY ancestor (``panda_hand`` for the Panda) and its descendants
    (``panda_leftfinger``, ``panda_rightfinger``).
    """
    fm = robot.full_model
    fid = fm.getFrameId(robot.grasp_frame)
    root = fid
    k = int(fm.frames[fid].parentFrame)
    while k != root and k > 0:
        if fm.frames[k].type == pin.FrameType.BODY:
            root = k
            break
        k = int(fm.frames[k].parentFrame)
    names: set[str] = set()
    for i, f in enumerate(fm.frames):
        j, seen = i, set()
        while j not in seen:
            if j == root:
                if f.type == pin.FrameType.BODY:
                    names.add(f.name)
                break
            seen.add(j)
            if j == 0:
                break
            j = int(fm.frames[j].parentFrame)
    return names
