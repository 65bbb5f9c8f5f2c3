"""The collision checker: batched checks of robot configurations in three modes.

The robot's collision meshes come from the same example-robot-data files as its
kinematic model (:meth:`Robot.build_geometry`), reduced with the same locked
joints (the Panda's fingers are locked *open*, as given in the robot spec). The
world is a list of :class:`~gcm_pipeline.robot.collision.world.WorldShape`
objects in the robot's base frame. This module takes plain shapes and arrays;
it knows no config. Which pairs are checked in which mode:
:mod:`~gcm_pipeline.robot.collision.pairs`; the broad phase:
:mod:`~gcm_pipeline.robot.collision.broadphase`.

**Narrow phase**: coal, through
``pin.computeCollisionsInParallel`` on a pool holding the pair's two
geometries, only for the (configuration, pair) entries the broad phase left
open. Two geometries within coal's GJK tolerance (1e-6 m) of each other count
as touching: asked without contact information, coal can otherwise answer
"free" for overlaps of any depth
(:func:`~gcm_pipeline.robot.collision.pairs.checker_requests`). A pair with
a robot mesh is first checked on the convex hulls of its meshes
(:func:`~gcm_pipeline.robot.collision.pairs.hull_pair_pool`), where they touch
on the hulls of a long mesh's pieces
(:func:`~gcm_pipeline.robot.collision.pairs.hull_pieces`): coal's mesh test
runs only where those touch. Batches of fewer than ``_FEW``
configurations (``_FEW_COMPILED`` with the compiled kernels) go to coal's own
broad phase (AABB-tree pools) instead, which costs less to set up, and so do
all batches of a checker with ``threads`` > 1 (those pools run in parallel in
C++; the NumPy broad phase does not). A pair of two
geometries fixed to the world (the base link against an obstacle that
overlaps it) collides in every configuration or in none: it is decided once,
when the checker is built, and so is a link that no joint lifts or lowers over a
world box it clears at home (a UR's shoulder over the table:
:mod:`~gcm_pipeline.robot.collision.apart`), free in every configuration.
:meth:`CollisionChecker.clearance`
(:mod:`~gcm_pipeline.robot.collision.clearance`) uses the same
spheres as lower bounds and runs coal's exact distance only for pairs that can
still be the nearest.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import coal
import numpy as np
import pinocchio as pin

from gcm_pipeline.errors import ConfigError, InputError, choice_error
from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.chain import JointFrames
from gcm_pipeline.robot.collision.apart import pairs_apart
from gcm_pipeline.robot.collision.broadphase import (
    BLOCK,
    BROAD_MARGIN,
    COMPILED_BLOCK,
    Screen,
    ShapeBound,
)
from gcm_pipeline.robot.collision.clearance import ClearanceQueries
from gcm_pipeline.robot.collision.contact import SolidMesh, interior_point, mesh_arrays
from gcm_pipeline.robot.collision.pairs import (
    GJK_MARGIN,
    KINDS,
    MODE_BIT,
    MODES,
    REASON_OBJECT,
    REASONS,
    Pair,
    checked_pairs,
    checker_requests,
    coal_transform,
    gripper_links,
    pair_pool,
    robot_geometry,
    tree_pool,
)
from gcm_pipeline.robot.collision.spheres import (
    SphereCover,
    geometry_mesh,
    robot_covers,
    sphere_cover,
)
from gcm_pipeline.robot.collision.world import WorldShape
from gcm_pipeline.robot.model import Robot

__all__ = ["CollisionChecker"]

#: The kinds a world shape may have.
_WORLD_KINDS = ("environment", "object")
#: The reasons as a fixed-width string array (no object arrays to convert).
_REASON_DTYPE = f"<U{max(len(r) for r in REASONS.values())}"
#: Fewer configurations than this go to coal's AABB-tree pools instead of the
#: NumPy broad phase (its set-up costs about as much as 100 configurations).
_FEW = 128
#: The same with the compiled kernels: their set-up (about 100 us on the Panda's
#: bottle scene) costs less than coal's pools from about 16 configurations on.
_FEW_COMPILED = 16
#: A link is dropped against a box it clears by more than the broad phase's margin
#: plus this at home, its height over the box unchanged by any joint [m].
_APART_SLACK = 1e-6


class _CarriedObject(NamedTuple):
    shape: WorldShape
    cover: SphereCover  # in the object geometry's frame
    environment: list[int]  # world geometries it may hit
    arm: list[int]  # robot geometries it may hit (not the gripper)


class CollisionChecker(ClearanceQueries):
    """Batched collision checks and clearance of robot configurations (see the module doc).

    Args:
        robot: The robot (its reduced model and collision geometry).
        world: The world shapes in the robot's base frame (at most one of kind
            ``object``).
        contact_tolerance: How deep the gripper may press into the object at
            the grasp [m], >= 0.
        self_collision: Check the robot against itself.
        threads: Threads of ``pin.computeCollisionsInParallel``; with more than one,
            every batch goes to coal's AABB-tree pools (parallel in C++).

    Raises:
        ConfigError: A negative contact tolerance or more than one object.

    Attributes:
        robot: The robot.
        world: The world shapes.
        geom_model: ``pin.GeometryModel`` with the robot links, the eroded
            gripper pieces (mesh object), the world shapes and *every* pair of
            the ``grasp`` mode active; usable with ``pin.computeCollisions``
            (on data prepared by :func:`~gcm_pipeline.robot.collision.pairs.checker_requests`
            for the checker's answers).
        pair_kind: Kind of each pair of ``geom_model.collisionPairs`` (P,) str.
        n_robot_geoms: Number of robot geometries (the first ones of ``geom_model``).
        gripper_geoms: Indices of the gripper geometries.
        link_names: Link of each robot geometry.
        table_exempt: Base links not checked against the support shape.
        contact_tolerance: [m].
        static_collisions: ``(robot link, world shape)`` pairs fixed to the
            world that collide (an obstacle overlapping the base link): every
            configuration collides.
        pairs_apart: ``(robot link, world shape)`` pairs no configuration
            brings together, not checked (:mod:`~gcm_pipeline.robot.collision.apart`).
    """

    def __init__(
        self,
        robot: Robot,
        world: Any = (),
        *,
        contact_tolerance: float = 0.005,
        self_collision: bool = True,
        threads: int = 1,
    ) -> None:
        self.robot = robot
        self.world = tuple(world)
        self.threads = max(1, int(threads))
        self.self_collision = bool(self_collision)
        tol = float(contact_tolerance)
        if not math.isfinite(tol) or tol < 0:
            raise ConfigError(f"environment.contact_tolerance must be >= 0 [m], got {tol!r}")
        self.contact_tolerance = tol
        objects = [s for s in self.world if s.kind == "object"]
        if len(objects) > 1:
            raise ConfigError(f"at most one object shape, got {[s.name for s in objects]}")
        for s in self.world:
            if s.kind not in _WORLD_KINDS:
                where = f"world shape {s.name!r}: "
                raise choice_error(ConfigError, "kind", s.kind, _WORLD_KINDS, prefix=where)
        self.object = objects[0] if objects else None

        model = robot.model
        gm = robot_geometry(robot)
        self.n_robot_geoms = n_rob = int(gm.ngeoms)
        robot_ids = list(range(n_rob))
        link_of = [model.frames[g.parentFrame].name for g in gm.geometryObjects]
        joint_of = [int(g.parentJoint) for g in gm.geometryObjects]
        self.link_names = tuple(link_of)
        self.gripper_geoms = tuple(i for i in robot_ids if link_of[i] in gripper_links(robot))
        gripper = set(self.gripper_geoms)

        checked = checked_pairs(robot, gm, self.world, self.gripper_geoms, tol, self.self_collision)
        pairs, world_ids = checked.pairs, checked.world_ids
        self.table_exempt = checked.table_exempt
        self._pairs = pairs
        self._gm = gm

        self._pair_modes = np.array([p.modes for p in pairs], dtype=int)
        self._pair_kind = np.array([p.kind for p in pairs], dtype=object)

        # sphere covers (broad phase, clearance bounds, the carried object)
        self._frames = JointFrames(model)
        # the robot's own sphere covers and hull vertices: computed once per robot
        cover = robot.cache.get("collision_cover")
        if cover is None:
            cover = robot.cache["collision_cover"] = robot_covers(
                gm, robot_ids, self._frames, max_spheres=8
            )
        self._cover = cover
        #: _place's grouping of points by joint, by the joints' bytes
        self._groups = {}
        #: the arguments of the compiled broad phase, by screen (see _compiled_screen)
        self._compiled_args = {}
        self._bounds = {
            w: ShapeBound(
                gm.geometryObjects[w].geometry, gm.geometryObjects[w].placement.homogeneous
            )
            for w in {p.b for p in pairs if p.kind != "self"}
        }
        self._hulls = robot.cache.setdefault("collision_hulls", {})
        self._edge_cache = robot.cache.setdefault("collision_edges", {})
        #: the narrow phase's convex-hull pre-check: pools by pair, hulls by geometry
        #: (built when a pair first reaches coal)
        self._model = model
        self._hull_pools = {}
        self._piece_pools = {}
        self._mesh_hulls = {}
        self._init_pools(pairs, link_of)

        # the mesh object as a solid: pieces wholly inside it
        self._init_solid(gm, world_ids)

        # every grasp-mode pair in one model (for colliding_pairs and independent checks)
        full = gm.copy()
        full.removeAllCollisionPairs()
        kinds: list[str] = []
        for kind in KINDS:
            for p in pairs:
                if p.kind == kind and p.modes & MODE_BIT["grasp"]:
                    full.addCollisionPair(pin.CollisionPair(p.a, p.b))
                    kinds.append(kind)
        self.geom_model = full
        self.pair_kind = np.array(kinds, dtype=object)
        self._data = model.createData()
        self._full_data = checker_requests(pin.GeometryData(full))

        self._init_clearance(gm, pairs, world_ids, joint_of, gripper)

        # the carried object (retreat): its cover in its own frame and its pairs
        self._carried = None
        obj = self.object
        if obj is not None:
            pts, tris = geometry_mesh(obj.geometry)
            self._carried = _CarriedObject(
                obj,
                sphere_cover(pts, tris, max_spheres=8),
                [world_ids[s.name] for s in self.world if s.kind == "environment"],
                [i for i in robot_ids if i not in gripper],
            )

    # --- construction helpers ---------------------------------------------------------

    def _init_pools(self, pairs: list[Pair], link_of: list[str]) -> None:
        """The narrow phase's pools, the static pairs and each mode's broad phase."""
        model, gm, robot = self.robot.model, self._gm, self.robot
        # the narrow phase: one pool per pair (its two geometries only)
        self._pair_pool = [pair_pool(model, gm, p, self.threads) for p in pairs]
        # pairs of two geometries fixed to the world (the base link against an obstacle)
        # collide in every configuration or in none: decided once, here
        fixed = [
            k
            for k, p in enumerate(pairs)
            if gm.geometryObjects[p.a].parentJoint == 0 and gm.geometryObjects[p.b].parentJoint == 0
        ]
        static_hit = {
            k
            for k in fixed
            if self._run(self._pair_pool[k], np.asarray(robot.home, dtype=float)[None])[0]
        }
        # a link that no joint lifts or lowers over a box's face (a UR's shoulder over
        # the table): above it at home, above it always (level 3 would call it free in
        # every configuration): not checked at all
        apart = pairs_apart(robot, gm, pairs, BROAD_MARGIN + _APART_SLACK)
        moving = [k for k in range(len(pairs)) if k not in fixed and k not in apart]
        self.pairs_apart, self.static_collisions = (
            tuple(
                (link_of[pairs[k].owner], gm.geometryObjects[pairs[k].b].name) for k in sorted(ks)
            )
            for ks in (apart, static_hit)
        )
        # a few configurations: coal's own broad phase (an AABB tree) per mode, and per
        # mode and kind for the reason of those that collide (no NumPy set-up cost)
        self._mode_pool: dict[int, Any] = {}
        self._kind_pool: dict[tuple[int, str], Any] = {}
        self._screens: dict[int, Screen] = {}
        self._static_reason: dict[int, str] = {}
        for bit in MODE_BIT.values():
            cols = [k for k in moving if pairs[k].modes & bit]
            active = [pairs[k] for k in cols]
            if active:
                self._mode_pool[bit] = tree_pool(model, gm, active, self.threads)
            for kind in KINDS:
                some = [p for p in active if p.kind == kind]
                if some:
                    self._kind_pool[bit, kind] = tree_pool(model, gm, some, self.threads)
            self._screens[bit] = self._screen(cols)
            hit_kinds = {pairs[k].kind for k in static_hit if pairs[k].modes & bit}
            first = next((kind for kind in KINDS if kind in hit_kinds), None)
            if first is not None:
                self._static_reason[bit] = REASONS[first]

    def _init_solid(self, gm: Any, world_ids: dict[str, int]) -> None:
        """Inside test of a mesh object for the robot pieces of the object pairs.

        coal checks a mesh object as its triangles; a robot piece (an arm link,
        a gripper piece) that lies wholly inside the closed mesh crosses none of
        them. Such a piece is found by testing one of its points
        (:func:`~gcm_pipeline.robot.collision.contact.interior_point`) against the solid
        (:class:`~gcm_pipeline.robot.collision.contact.SolidMesh`).
        """
        self._solid: SolidMesh | None = None
        obj = self.object
        if obj is None or not isinstance(obj.geometry, coal.BVHModelBase):
            return
        w = world_ids[obj.name]
        rows = [k for k, p in enumerate(self._pairs) if p.kind == "object" and p.b == w]
        if not rows:
            return
        self._solid = SolidMesh(*mesh_arrays(obj.geometry))
        self._solid_from_base = np.linalg.inv(obj.placement)
        self._solid_pair = np.array(rows, dtype=int)
        pieces = [gm.geometryObjects[self._pairs[k].a] for k in rows]
        self._solid_names = tuple(go.name for go in pieces)
        self._solid_joint = np.array([int(go.parentJoint) for go in pieces], dtype=int)
        self._solid_local = np.array(
            [
                self._frames.local(
                    int(go.parentJoint), np.eye(3), go.placement.act(interior_point(go.geometry))
                )[1]
                for go in pieces
            ]
        )

    # --- placing points -------------------------------------------------------------------

    def _run(self, pool: Any, q: np.ndarray) -> np.ndarray:
        """Whether each configuration (M, nq) collides for the pairs of ``pool``, (M,) bool."""
        if len(q) == 0:
            return np.zeros(0, dtype=bool)
        res = pin.computeCollisionsInParallel(
            self.threads, pool, np.asfortranarray(q.T), True, False
        )
        return np.asarray(res, dtype=bool).reshape(len(q))

    # --- queries --------------------------------------------------------------------------

    def check(self, q: Any, mode: str = "grasp", carried: Any = None) -> np.ndarray:
        """Collision reason of each configuration.

        Args:
            q: Configurations (N, nq) or (nq,) [rad]. Non-finite rows are skipped
                (reason ``''``); the caller marks them unreachable anyway.
            mode: ``grasp`` (the gripper may touch the object by the contact
                tolerance), ``approach`` (no contact) or ``retreat`` (the gripper
                holds the object, carried along, see ``carried``).
            carried: ``retreat`` only: the pose of the object in the grasp frame,
                (N, 4, 4) or (4, 4) (``inv(T_grasp) @ T_object`` at the grasp);
                None: the object is not checked.

        Returns:
            (N,) str: ``''`` (free), ``'collision_environment'``,
            ``'collision_self'`` or ``'collision_object'`` (first that applies,
            in this order).

        Raises:
            InputError: Unknown mode or ``carried`` of the wrong shape.
        """
        if mode not in MODE_BIT:
            raise choice_error(InputError, "collision mode", mode, MODES)
        qs = self.robot.as_configurations(q)
        n = len(qs)
        held = None
        if carried is not None and mode == "retreat" and self._carried is not None:
            held = np.broadcast_to(np.asarray(carried, dtype=float), (n, 4, 4))
        reason = np.full(n, "", dtype=_REASON_DTYPE)
        rows = np.flatnonzero(np.all(np.isfinite(qs), axis=1))
        # the compiled levels keep no large temporaries: larger blocks, fewer calls per pair
        step = BLOCK if kernels.get() is None else COMPILED_BLOCK
        for a in range(0, rows.size, step):
            block = rows[a : a + step]
            reason[block] = self._check_block(
                qs[block], MODE_BIT[mode], None if held is None else held[block]
            )
        return reason

    def _check_block(self, q: np.ndarray, bit: int, held: np.ndarray | None) -> np.ndarray:
        n = len(q)
        reason = np.full(n, "", dtype=_REASON_DTYPE)
        # the mesh object and a carried object decide on the frames without a margin:
        # libm's cosines then, the NumPy code's frames to the bit (see JointFrames.compute)
        exact = self._solid is not None or held is not None
        all_frames = None
        if n < (_FEW if kernels.get() is None else _FEW_COMPILED) or self.threads > 1:
            pool = self._mode_pool.get(bit)
            todo = np.flatnonzero(self._run(pool, q)) if pool is not None else np.zeros(0, int)
            for kind in KINDS:
                kind_pool = self._kind_pool.get((bit, kind))
                if kind_pool is None or todo.size == 0:
                    continue
                hit = self._run(kind_pool, q[todo])
                reason[todo[hit]] = REASONS[kind]
                todo = todo[~hit]
        else:
            screen = self._screens[bit]
            all_frames = self._frames.compute(q, libm=exact)
            # each configuration's first kind of collision only: its reason
            by_pair = self._pair_hits(q, all_frames, screen, first=True).T  # (P, N)
            left = np.ones(n, dtype=bool)  # no reason yet
            for kind in KINDS:
                some = by_pair[screen.kind == kind].any(axis=0) & left
                reason[some] = REASONS[kind]
                left &= ~some
        static = self._static_reason.get(bit)
        if static is not None:
            # a static pair collides in every configuration: its kind unless an earlier one
            order = [REASONS[k] for k in KINDS]
            later = np.isin(reason, ["", *order[order.index(static) + 1 :]])
            reason[later] = static
        free = np.flatnonzero(reason == "")
        if free.size and exact:
            if all_frames is None:
                frames = self._frames.compute(q[free], libm=True)
            else:
                frames = all_frames.take(free)
            if self._solid is not None:
                inside = self._inside_object(frames, np.arange(free.size), bit)
                reason[free[inside]] = REASON_OBJECT
            if held is not None:
                still = np.flatnonzero(reason[free] == "")
                sub = frames.take(still)
                grasp_pose = self.robot.fk(q[free[still]])
                for kind in ("environment", "object"):
                    hit = self._carried_collides(kind, sub, grasp_pose, held[free[still]])
                    reason[free[still[hit]]] = REASONS[kind]
                    still, grasp_pose = still[~hit], grasp_pose[~hit]
                    sub = sub.take(np.flatnonzero(~hit))
                    if still.size == 0:
                        break
        return reason

    def _inside_object(self, frames: Any, rows: np.ndarray, bit: int) -> np.ndarray:
        """Whether an active robot piece lies inside the mesh object, (M,) bool."""
        out = np.zeros(rows.size, dtype=bool)
        use = np.flatnonzero(self._pair_modes[self._solid_pair] & bit)
        if self._solid is None or rows.size == 0 or use.size == 0:
            return out
        sub = frames.take(rows)
        pts = self._place(sub, self._solid_joint[use], self._solid_local[use])
        m = self._solid_from_base
        local = pts @ m[:3, :3].T + m[:3, 3]
        inside = self._solid.contains(local.reshape(-1, 3)).reshape(pts.shape[:2])
        return np.asarray(inside.any(axis=1), dtype=bool)

    def _carried_collides(
        self, kind: str, frames: Any, grasp_pose: np.ndarray, held: np.ndarray
    ) -> np.ndarray:
        """The carried object against the environment or the arm links, (M,) bool.

        Sphere covers rule out most pairs; coal decides the others.
        """
        m = grasp_pose.shape[0]
        out = np.zeros(m, dtype=bool)
        car = self._carried
        if car is None or m == 0:
            return out
        pose = grasp_pose @ held  # the object in the base frame
        centres = car.cover.centres @ np.swapaxes(pose[:, :3, :3], 1, 2) + pose[:, None, :3, 3]
        gm = self._gm
        # the checker's rule for every narrow-phase answer (pairs.checker_requests)
        req = coal.CollisionRequest()
        req.gjk_tolerance = GJK_MARGIN
        req.security_margin = GJK_MARGIN
        res = coal.CollisionResult()
        obj_geom = car.shape.geometry
        if kind == "environment":
            for w in car.environment:
                lb = (self._bounds_for(w).lower(centres) - car.cover.radii).min(axis=1)
                go = gm.geometryObjects[w]
                tf_w = coal_transform(go.placement.homogeneous)
                for i in np.flatnonzero((lb <= BROAD_MARGIN) & ~out).tolist():
                    res.clear()
                    if coal.collide(obj_geom, coal_transform(pose[i]), go.geometry, tf_w, req, res):
                        out[i] = True
            return out
        cov = self._cover
        cw = self._place(frames, cov.joint, cov.centre)
        for g in car.arm:
            s = np.arange(cov.start[g], cov.start[g + 1])
            gap = np.linalg.norm(cw[:, s, None, :] - centres[:, None, :, :], axis=3)
            lb = (gap - cov.radius[s][:, None] - car.cover.radii[None, :]).min(axis=(1, 2))
            go = gm.geometryObjects[g]
            j = int(go.parentJoint)
            rl, tl = self._frames.local(
                j, np.asarray(go.placement.rotation), np.asarray(go.placement.translation)
            )
            for i in np.flatnonzero((lb <= BROAD_MARGIN) & ~out).tolist():
                tf = np.eye(4)
                tf[:3, :3] = frames[0][j][i] @ rl
                tf[:3, 3] = frames[1][j][i] + frames[0][j][i] @ tl
                res.clear()
                if coal.collide(
                    go.geometry, coal_transform(tf), obj_geom, coal_transform(pose[i]), req, res
                ):
                    out[i] = True
        return out

    def in_collision(self, q: Any, mode: str = "grasp") -> np.ndarray:
        """Whether each configuration collides (any kind), (N,) bool."""
        return self.check(q, mode) != ""

    def colliding_pairs(self, q: Any) -> list[tuple[str, str, str]]:
        """All colliding pairs of one configuration in the ``grasp`` mode (for reports).

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
            frames = self._frames.compute(qs[None], libm=True)  # as check decides
            inside = self._inside_pieces(frames)
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

    def _inside_pieces(self, frames: Any) -> np.ndarray:
        """Which grasp-mode pieces of one configuration lie inside the mesh object."""
        assert self._solid is not None
        use = self._pair_modes[self._solid_pair] & MODE_BIT["grasp"] > 0
        pts = self._place(frames, self._solid_joint, self._solid_local)[0]
        m = self._solid_from_base
        return self._solid.contains(pts @ m[:3, :3].T + m[:3, 3]) & use

    def with_world(self, world: Any) -> CollisionChecker:
        """The same robot and settings in another world (e.g. the object moved).

        The robot's collision geometry is read once per robot and reused.
        """
        return CollisionChecker(
            self.robot,
            world,
            contact_tolerance=self.contact_tolerance,
            self_collision=self.self_collision,
            threads=self.threads,
        )

    def __repr__(self) -> str:
        counts = {k: int(np.sum(self.pair_kind == k)) for k in KINDS}
        world = ", ".join(s.name for s in self.world) or "(none)"
        spheres = len(self._cover.radius)
        return (
            f"CollisionChecker(robot={self.robot.name!r}, world=[{world}], pairs={counts}, "
            f"contact_tolerance={self.contact_tolerance}, table_exempt={list(self.table_exempt)}, "
            f"spheres={spheres})"
        )
