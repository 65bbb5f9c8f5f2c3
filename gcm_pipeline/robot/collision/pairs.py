"""Which pairs are checked, in which modes, and the coal pools that check them.

Pairs that are checked, by kind (the ``reason`` a colliding configuration gets):

``collision_environment``
    every robot link vs every environment shape, except a support shape (the
    table) vs the robot's base links standing on it: links attached to the
    universe or to the first joint that touch it in the home configuration
    (``panda_link0``; ``panda_link1`` is 0.14 m above it and stays checked).
``collision_self``
    all link pairs on different joints, minus the pairs the SRDF disables
    (``pin.removeCollisionPairs``) and adjacent links (parent/child joints).
``collision_object``
    every robot link, the open fingers included, vs the object. The *gripper*
    (the robot's hand, :mod:`gcm_pipeline.robot.hand`: ``panda_hand`` and both
    fingers; a tool's shapes) may press into the object by ``contact_tolerance`` ``t``
    at the grasp (a finger pad closing on the surface is a grasp, not a collision):

    * a **primitive** object (cylinder, box, sphere, a thin box for a plane) is
      eroded exactly (radius / half-sizes minus ``t``) and checked against the
      gripper: the gripper collides when one of its points lies deeper than
      ``t`` inside the object. A 2 mm plane erodes to nothing, so the gripper
      may touch it;
    * for a **mesh** object each convex collision piece of the gripper is
      eroded by ``t`` instead (:mod:`gcm_pipeline.robot.collision.contact`) and checked
      against the original mesh: the gripper collides when a point of the
      object's surface lies deeper than ``t`` inside one of its pieces. This is
      never more conservative than the geometry, also for walls thinner than
      ``2 t`` (a mug's wall or handle), which an inward offset of the mesh
      cannot represent. A gripper piece that is not convex is checked
      uneroded (a warning says so).

    Arm links (not gripper) are checked against the full object. A closed mesh
    object is a solid: a piece lying wholly inside it, crossing none of its
    triangles, collides too.

When a configuration collides in more than one way, the reason is the first of
environment, self, object. A pair collides when coal finds its two geometries
overlapping or within its GJK tolerance, 1e-6 m, of each other
(:func:`checker_requests`).

**Modes** (:meth:`~gcm_pipeline.robot.collision.checker.CollisionChecker.check`):
``grasp`` is the above; ``approach`` allows no contact (the gripper against the
full object, as the arm); ``retreat`` is the grasp holding the object: the
gripper may touch it and the object moves with the grasp frame (``carried``),
checked against the environment (``collision_environment``) and the arm links
(``collision_object``).
"""

from __future__ import annotations

import warnings
from typing import Any, NamedTuple

import coal
import numpy as np
import pinocchio as pin

from gcm_pipeline.robot.collision.contact import NotConvexError, erode_convex, mesh_arrays
from gcm_pipeline.robot.collision.world import PRIMITIVES, WorldShape, erode_primitive
from gcm_pipeline.robot.model import Robot

__all__ = [
    "ALL_MODES",
    "COLLISION_REASONS",
    "KINDS",
    "MODES",
    "MODE_BIT",
    "REASONS",
    "REASON_ENVIRONMENT",
    "REASON_OBJECT",
    "REASON_SELF",
    "Pair",
    "PairSet",
    "add_eroded_gripper",
    "checked_pairs",
    "checker_requests",
    "coal_transform",
    "GJK_MARGIN",
    "HULL_MARGIN",
    "PIECES",
    "convex_hull",
    "gripper_links",
    "hull_pair_pool",
    "hull_pieces",
    "pair_pool",
    "robot_geometry",
    "se3",
    "self_pairs",
    "support_exempt",
    "tree_pool",
    "without_cached_guess",
]

REASON_SELF = "collision_self"
REASON_ENVIRONMENT = "collision_environment"
REASON_OBJECT = "collision_object"
COLLISION_REASONS = (REASON_SELF, REASON_ENVIRONMENT, REASON_OBJECT)

KINDS = ("environment", "self", "object")
REASONS = {"environment": REASON_ENVIRONMENT, "self": REASON_SELF, "object": REASON_OBJECT}

#: Checking modes: what the gripper may do with the object.
MODES = ("grasp", "approach", "retreat")
MODE_BIT = {"grasp": 1, "approach": 2, "retreat": 4}
ALL_MODES = 7


class Pair(NamedTuple):
    """One checked pair: geometry indices in the checker's model, and what bounds it."""

    kind: str
    a: int  # robot-side geometry (a link, or an eroded gripper piece)
    b: int  # world geometry, or the other link for self pairs
    owner: int  # robot geometry whose spheres bound ``a``
    other: int  # robot geometry whose spheres bound ``b`` (self pairs), else -1
    modes: int  # bit set of the modes the pair is checked in


class PairSet(NamedTuple):
    """The checked pairs of a robot in a world, and the world's geometries in the model.

    Attributes:
        pairs: The pairs (robot links first, then eroded gripper pieces, then world).
        world_ids: World shape name -> geometry index in the model.
        table_exempt: Base links not checked against the support shape.
    """

    pairs: list[Pair]
    world_ids: dict[str, int]
    table_exempt: tuple[str, ...]


def checked_pairs(
    robot: Robot,
    gm: Any,
    world: tuple[WorldShape, ...],
    gripper_geoms: tuple[int, ...],
    tol: float,
    self_collision: bool,
) -> PairSet:
    """Add the world (and the eroded gripper or object) to ``gm``; list the pairs to check.

    Args:
        robot: The robot.
        gm: Its collision geometry model (a copy: world geometries are added to it).
        world: The world shapes (at most one of kind ``object``).
        gripper_geoms: Indices of the gripper geometries in ``gm``.
        tol: The contact tolerance [m] >= 0.
        self_collision: Check the robot against itself.

    Returns:
        The :class:`PairSet`.
    """
    model = robot.model
    n_rob = int(gm.ngeoms)
    robot_ids = list(range(n_rob))
    link_of = [model.frames[g.parentFrame].name for g in gm.geometryObjects]
    joint_of = [int(g.parentJoint) for g in gm.geometryObjects]
    gripper = set(gripper_geoms)
    obj = next((s for s in world if s.kind == "object"), None)

    # world geometries (after the robot's and the eroded gripper pieces)
    mesh_object = obj is not None and not isinstance(obj.geometry, PRIMITIVES)
    eroded = add_eroded_gripper(gm, gripper_geoms, tol) if mesh_object else {}
    world_ids: dict[str, int] = {}
    for shape in world:
        go = pin.GeometryObject(shape.name, 0, 0, se3(shape.placement), shape.geometry)
        world_ids[shape.name] = int(gm.addGeometryObject(go))
    contact_id = None
    if obj is not None and not mesh_object:
        shrunk = erode_primitive(obj.geometry, tol) if tol > 0 else obj.geometry
        if shrunk is not None:
            go = pin.GeometryObject("object_contact", 0, 0, se3(obj.placement), shrunk)
            contact_id = int(gm.addGeometryObject(go))

    pairs: list[Pair] = []
    if self_collision:
        for a, b in self_pairs(robot, joint_of):
            pairs.append(Pair("self", a, b, a, b, ALL_MODES))
    exempt: set[int] = set()
    for shape in world:
        if shape.kind == "environment" and shape.support:
            exempt |= support_exempt(robot, gm, world_ids[shape.name], joint_of)
    table_exempt = tuple(sorted({link_of[i] for i in exempt}))
    for shape in world:
        if shape.kind != "environment":
            continue
        w = world_ids[shape.name]
        for i in robot_ids:
            if shape.support and i in exempt:
                continue
            pairs.append(Pair("environment", i, w, i, -1, ALL_MODES))
    if obj is not None:
        w = world_ids[obj.name]
        grasp, approach = MODE_BIT["grasp"], MODE_BIT["approach"]
        for i in robot_ids:
            if i not in gripper:
                # arm links vs the object where it stands (not while carried)
                pairs.append(Pair("object", i, w, i, -1, grasp | approach))
                continue
            pairs.append(Pair("object", i, w, i, -1, approach))  # no contact on the way in
            if mesh_object:
                piece = eroded[i]
                if piece is not None:
                    pairs.append(Pair("object", piece, w, i, -1, grasp))
            elif contact_id is not None:
                pairs.append(Pair("object", i, contact_id, i, -1, grasp))
    return PairSet(pairs, world_ids, table_exempt)


def robot_geometry(robot: Robot) -> Any:
    """A copy of the robot's collision geometry model (read once per robot)."""
    gm = robot.cache.get("collision_geometry")
    if gm is None:
        gm = robot.cache["collision_geometry"] = robot.build_geometry("collision")
    return gm.copy()


def self_pairs(robot: Robot, joint_of: list[int]) -> list[tuple[int, int]]:
    """Self pairs: all pairs minus the SRDF's disabled ones and same/adjacent links."""
    model = robot.model
    gm = robot_geometry(robot)
    gm.addAllCollisionPairs()
    if robot.srdf_path is not None:
        pin.removeCollisionPairs(model, gm, str(robot.srdf_path))
    out = []
    for cp in gm.collisionPairs:
        a, b = int(cp.first), int(cp.second)
        ja, jb = joint_of[a], joint_of[b]
        if ja == jb or model.parents[ja] == jb or model.parents[jb] == ja:
            continue  # same rigid body or adjacent links
        out.append((a, b))
    return out


def support_exempt(robot: Robot, gm: Any, support: int, joint_of: list[int]) -> set[int]:
    """Robot geometries not checked against a support: the base links standing on it.

    Links fixed to the universe or to the first joint that touch the support
    in the home configuration (for the Panda at z = 0: ``panda_link0``).
    """
    model = robot.model
    first = [i for i in range(len(joint_of)) if joint_of[i] in (0, 1)]
    if not first:
        return set()
    probe = gm.copy()
    probe.removeAllCollisionPairs()
    for i in first:
        probe.addCollisionPair(pin.CollisionPair(i, support))
    pd = checker_requests(pin.GeometryData(probe))
    pin.computeCollisions(model, model.createData(), probe, pd, robot.home, False)
    return {
        int(cp.first)
        for k, cp in enumerate(probe.collisionPairs)
        if pd.collisionResults[k].isCollision()
    }


def add_eroded_gripper(
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
                stacklevel=4,
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


def gripper_links(robot: Robot) -> set[str]:
    """Links of the gripper: the robot's hand (:mod:`gcm_pipeline.robot.hand`).

    The links of :attr:`~gcm_pipeline.robot.model.Robot.hand_links` (the Panda's
    ``panda_hand`` and both fingers) and, for a tool with collision shapes, the flange
    frame that carries them.
    """
    names = set(robot.hand_links)
    tool = robot.spec.tool
    if tool is not None and tool.collision:
        names.add(tool.flange)
    return names


def without_cached_guess(gd: Any) -> Any:
    """Geometry data whose GJK starts from the same guess every time.

    coal reuses the last query's solution as the next initial guess by
    default; an answer then depends on what was asked before (last bits of a
    distance, rarely a borderline contact), so the result of a configuration
    would depend on the chunking and the number of workers.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        for req in [*gd.collisionRequests, *gd.distanceRequests]:
            req.enable_cached_gjk_guess = False
            req.gjk_initial_guess = coal.GJKInitialGuess.DefaultGuess
    return gd


#: Distance [m] within which the narrow phase counts two geometries as touching:
#: coal's GJK tolerance (:func:`checker_requests`).
GJK_MARGIN = 1e-6


def checker_requests(gd: Any) -> Any:
    """Geometry data whose collision answers are the checker's: deterministic and complete.

    The GJK guess as in :func:`without_cached_guess`, and a security margin of
    :data:`GJK_MARGIN`, coal's GJK tolerance. Without contact information (as
    Pinocchio asks), coal's ``collide`` ends GJK with "collision" when the origin
    lies within that tolerance of GJK's simplex, which can happen at any depth,
    and then returns the leftover distance (> 0) as the answer: two overlapping
    cylinders of a user arm came back free 0.58 mm deep (coal 3.0.3; with contact
    information EPA runs and finds the depth). With the margin, every such end
    counts as contact, as EPA would say, at the price of calling geometries
    within 1e-6 m of each other touching.
    """
    without_cached_guess(gd)
    for req in gd.collisionRequests:
        req.gjk_tolerance = GJK_MARGIN
        req.security_margin = max(float(req.security_margin), GJK_MARGIN)
    return gd


def tree_pool(model: Any, gm: Any, pairs: list[Pair], threads: int) -> Any:
    """A pool checking ``pairs`` with coal's dynamic AABB tree (broad phase) in C++."""
    km = gm.copy()
    km.removeAllCollisionPairs()
    for p in pairs:
        km.addCollisionPair(pin.CollisionPair(p.a, p.b))
    pool = pin.TreeBroadPhaseManagerPool_DynamicAABBTreeCollisionManager(model, km, threads)
    for i in range(pool.size()):
        checker_requests(pool.getGeometryData(i))
    return pool


def pair_pool(model: Any, gm: Any, pair: Pair, threads: int) -> Any:
    """A pool checking one pair with coal's narrow phase (a model of its two geometries)."""
    km = pin.GeometryModel()
    for g in (pair.a, pair.b):
        km.addGeometryObject(gm.geometryObjects[g])
    km.addCollisionPair(pin.CollisionPair(0, 1))
    pool = pin.GeometryPool(model, km, threads)
    for i in range(pool.size()):
        checker_requests(pool.getGeometryData(i))
    return pool


#: Distance [m] below which a pair's convex hulls count as touching in
#: :func:`hull_pair_pool` (far above coal's GJK tolerance, 1e-6).
HULL_MARGIN = 1e-4


#: Thinnest spread of a point set (its smallest singular value over its largest) that
#: coal's convex hull is asked to hull: coal 3 crashes (a segmentation fault, no
#: exception) on a flat set, and on one 1e-9 thick; 1e-6 was hulled.
SOLID_SPREAD = 1e-4


def _solid(points: np.ndarray) -> bool:
    """Whether points (K, 3) span a volume that coal can hull (:data:`SOLID_SPREAD`)."""
    if len(points) < 4:
        return False
    spread = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return bool(spread[2] > SOLID_SPREAD * spread[0])


def convex_hull(geometry: Any) -> Any:
    """The convex hull (a ``coal.ConvexBase``) of a coal mesh's vertices; None if it has none.

    Only a ``BVHModelBase`` (a mesh) has one here; primitives, convex pieces and
    octrees give None, and so does a flat mesh (:data:`SOLID_SPREAD`).
    """
    if not isinstance(geometry, coal.BVHModelBase):
        return None
    if not _solid(np.asarray(geometry.vertices(), dtype=float).reshape(-1, 3)):
        return None  # flat: coal would crash; no hull, no pre-check
    try:
        mesh = geometry.clone()
        mesh.buildConvexHull(True, "Qt")
        return mesh.convex
    except Exception:  # a degenerate mesh (flat, too few points): no hull, no pre-check
        return None


#: Pieces a long robot mesh is cut into for the convex-hull pre-check (:func:`hull_pieces`).
PIECES = 3


def hull_pieces(geometry: Any, pieces: int = PIECES) -> list[Any] | None:
    """Convex hulls (``coal.ConvexBase``) whose union holds a coal mesh; None if it has none.

    A long mesh (its vertices' longest extent more than twice the next: an arm
    link) is cut across that extent into ``pieces`` slabs of equal width, each
    triangle going to the slab of its centroid, and each slab's triangles get
    their own hull: every triangle lies in its piece's hull, so the hulls hold
    the mesh, closer than one hull does where the link is concave (the UR5's
    forearm between its two joints). Any other mesh, or a piece qhull cannot
    hull (flat: :data:`SOLID_SPREAD`), gives the whole mesh's :func:`convex_hull`.
    """
    whole = convex_hull(geometry)
    if whole is None or pieces < 2:
        return None if whole is None else [whole]
    verts, tris = mesh_arrays(geometry)
    used = verts[np.unique(tris)]
    extent = np.sort(used.max(axis=0) - used.min(axis=0))
    if extent[2] <= 2.0 * extent[1]:
        return [whole]
    axis = int(np.argmax(used.max(axis=0) - used.min(axis=0)))
    centre = verts[tris].mean(axis=1)[:, axis]
    lo, hi = used[:, axis].min(), used[:, axis].max()
    slab = np.clip(((centre - lo) / (hi - lo) * pieces).astype(int), 0, pieces - 1)
    out = []
    for k in range(pieces):
        points = verts[np.unique(tris[slab == k])]
        if not _solid(points):  # a flat piece (a cap's triangles only): coal would crash
            return [whole]
        vec = coal.StdVec_Vec3s()
        for point in points:
            vec.append(point)
        out.append(coal.Convex.convexHull(vec, True, "Qt"))
    return out


def hull_pair_pool(
    model: Any,
    gm: Any,
    pair: Pair,
    threads: int,
    hulls: dict[tuple[int, int], Any],
    pieces: int = 1,
) -> Any:
    """A pool checking one pair with each mesh replaced by its convex hull, or None.

    With ``pieces`` > 1, each long mesh is replaced by the hulls of its pieces
    (:func:`hull_pieces`) and every piece of one side is checked against every
    piece of the other: the pool's answer is whether any of them touch. Its
    collision requests count the hulls as touching within :data:`HULL_MARGIN`;
    the hulls hold their mesh, so a configuration this pool finds free is free
    for :func:`pair_pool` too. None when neither geometry is a mesh (with
    ``pieces`` > 1: neither is cut into pieces), or when the world side of the
    pair is not a primitive (a mesh, a point cloud). ``hulls`` caches the hulls
    of each geometry index and piece count (None: no hull).
    """
    if pair.kind != "self" and not isinstance(gm.geometryObjects[pair.b].geometry, PRIMITIVES):
        # a world mesh or point cloud: its hull would touch the robot wherever the
        # shape is concave (a mug's opening), doubling coal's calls
        return None
    sides = []
    for g in (pair.a, pair.b):
        go = gm.geometryObjects[g]
        if (g, pieces) not in hulls:
            hulls[g, pieces] = hull_pieces(go.geometry, pieces)
        own = hulls[g, pieces]
        if own is None:
            sides.append([go])
        else:
            sides.append(
                [
                    pin.GeometryObject(go.name, go.parentJoint, go.parentFrame, go.placement, h)
                    for h in own
                ]
            )
    if all(hulls[g, pieces] is None for g in (pair.a, pair.b)):
        return None
    if pieces > 1 and len(sides[0]) == 1 and len(sides[1]) == 1:
        return None  # no piece closer than the whole hull
    km = pin.GeometryModel()
    for go in [*sides[0], *sides[1]]:
        km.addGeometryObject(go)
    first = len(sides[0])
    for i in range(first):
        for j in range(len(sides[1])):
            km.addCollisionPair(pin.CollisionPair(i, first + j))
    pool = pin.GeometryPool(model, km, threads)
    for i in range(pool.size()):
        gd = checker_requests(pool.getGeometryData(i))
        for req in gd.collisionRequests:
            req.security_margin = HULL_MARGIN
    return pool


def coal_transform(m: np.ndarray) -> Any:
    """A (4, 4) transform as a ``coal.Transform3s``."""
    return coal.Transform3s(np.ascontiguousarray(m[:3, :3]), np.ascontiguousarray(m[:3, 3]))


def se3(m: np.ndarray) -> pin.SE3:
    """A (4, 4) transform as a ``pin.SE3``."""
    return pin.SE3(np.ascontiguousarray(m[:3, :3]), np.ascontiguousarray(m[:3, 3]))
