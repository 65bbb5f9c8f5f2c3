"""Acceptance: realistic antipodal grasps on a thin-walled mug, imported as an ACRONYM file.

The grasps are made here the way ACRONYM makes its successful ones: antipodal contact
pairs on the mesh (opposite normals within a 15 deg friction cone, opening <= 78 mm),
approached from any side around the contact axis, fingertips up to 45 mm past the
contacts (so the rim reaches toward the palm), and kept only when the open Panda gripper
(its example-robot-data collision pieces) stays >= 1 mm clear of the mesh. They are
written to an ACRONYM HDF5 file (with some failed grasps to drop) and read back by
``format: acronym`` with ACRONYM's Franka frame mapped by ``grasp_to_tool``.

An independent check (the unreduced example-robot-data model with its own SRDF pairs,
coal's complete answer (contact information on) on the original mesh and on the table,
Pinocchio FK and joint limits) decides which grasps have a collision-free IK solution:
a grasp is *reachable in truth* when any IK candidate found with a generous seed budget
passes it. The pipeline, with default settings, must report at least 99 % of those
reachable (recall) and none it reports reachable may fail the check (0 false positives).
"""

from __future__ import annotations

import coal
import example_robot_data
import numpy as np
import pinocchio as pin
import pytest

import gcm_pipeline as gcm
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.robot.ik import solve_ik

trimesh = pytest.importorskip("trimesh")
h5py = pytest.importorskip("h5py")
from helpers import complete_answers  # noqa: E402
from thin_walled import coal_transform, cup_parts, to_bvh  # noqa: E402

BASE_TO_TCP = 0.1034  # [m] ACRONYM's Franka hand base -> fingertip midpoint
MUG_POSE = {"xyz": [0.45, -0.15, 0.0], "rpy_deg": [0, 0, 40]}
CLEARANCE = 0.001  # [m] the open gripper's distance to the mesh in every kept grasp


def _solid(geometry):
    if isinstance(geometry, coal.BVHModelBase):  # the Panda's hand: a convex hull, as a solid
        vec = coal.StdVec_Vec3s()
        for p in np.asarray(geometry.vertices(), dtype=float):
            vec.append(p)
        return coal.Convex.convexHull(vec, True, "Qt")
    return geometry


def _gripper_pieces():
    """The open Panda gripper's collision pieces as (solid, pose relative to panda_hand_tcp)."""
    erd = example_robot_data.load("panda")
    model, gm = erd.model, erd.collision_model
    data, gd = model.createData(), pin.GeometryData(gm)
    q = pin.neutral(model)
    q[model.joints[model.getJointId("panda_finger_joint1")].idx_q] = 0.04
    q[model.joints[model.getJointId("panda_finger_joint2")].idx_q] = 0.04
    pin.framesForwardKinematics(model, data, q)
    pin.updateGeometryPlacements(model, data, gm, gd, q)
    tcp_inv = np.linalg.inv(data.oMf[model.getFrameId("panda_hand_tcp")].homogeneous)
    out = []
    for k, go in enumerate(gm.geometryObjects):
        if model.frames[go.parentFrame].name in (
            "panda_hand",
            "panda_leftfinger",
            "panda_rightfinger",
        ):
            out.append((_solid(go.geometry), tcp_inv @ gd.oMg[k].homogeneous))
    assert len(out) == 9
    return out


def _gap(pieces, bvh, tcp, depth):
    """Smallest distance [m] of the open gripper to the mesh, fingertips ``depth`` past tcp."""
    tool = tcp @ TOOL_FROM_BASE_AXES
    tool[:3, 3] += depth * tcp[:3, 2]
    gap = np.inf
    for solid, rel in pieces:
        res = coal.DistanceResult()
        d = coal.distance(
            solid, coal_transform(tool @ rel), bvh, coal.Transform3s(), coal.DistanceRequest(), res
        )
        gap = min(gap, d)
    return gap


#: ACRONYM's base frame axes (fingers along x) -> panda_hand_tcp's (fingers along y): Rz(-90 deg)
TOOL_FROM_BASE_AXES = np.array([[0.0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])


def sample_antipodal_grasps(parts, n, seed=0):
    """ACRONYM-like successful grasps (hand base frame, object frame) and some failures."""
    rng = np.random.default_rng(seed)
    whole = trimesh.util.concatenate(parts)
    bvh = to_bvh(whole)
    pieces = _gripper_pieces()
    tool_from_base = np.eye(4)
    tool_from_base[2, 3] = BASE_TO_TCP
    good, bad = [], []
    for _ in range(60):  # rounds of candidates, until n good grasps
        for k, part in enumerate(parts):
            pts, face = trimesh.sample.sample_surface(part, 400, seed=int(rng.integers(1 << 31)))
            normals = part.face_normals[face]
            others = [p for j, p in enumerate(parts) if j != k]
            outer = np.ones(len(pts), dtype=bool)
            for other in others:  # contacts on the visible surface only
                outer &= ~other.contains(pts + 1e-4 * normals)
            hit, ray, tri = part.ray.intersects_location(
                pts[outer] - 1e-5 * normals[outer], -normals[outer], multiple_hits=False
            )
            rows = np.flatnonzero(outer)[ray]
            p1, p2 = pts[rows], hit
            n2 = part.face_normals[tri]
            width = np.linalg.norm(p2 - p1, axis=1)
            closing = (p2 - p1) / np.maximum(width, 1e-12)[:, None]
            cone = np.cos(np.radians(15))
            ok = (width > 1e-3) & (width < 0.078)
            ok &= (-(normals[rows] * closing).sum(1) > cone) & ((n2 * closing).sum(1) > cone)
            for a, b, x in zip(p1[ok], p2[ok], closing[ok], strict=True):
                if len(good) >= n:
                    break
                e1 = np.cross(x, [0.0, 0.0, 1.0] if abs(x[2]) < 0.9 else [1.0, 0.0, 0.0])
                e1 /= np.linalg.norm(e1)
                e2 = np.cross(x, e1)
                theta = rng.uniform(0, 2 * np.pi)
                z = np.cos(theta) * e1 + np.sin(theta) * e2
                tcp = np.eye(4)
                tcp[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)  # base frame axes
                tcp[:3, 3] = 0.5 * (a + b)
                # ACRONYM's depth: push the open hand along its approach as far as it goes,
                # up to the finger length, stopping CLEARANCE short of the mesh (conservative
                # advancement: a move by s along z changes no distance by more than s)
                depth, free = 0.0, False
                for _ in range(12):
                    gap = _gap(pieces, bvh, tcp, depth)
                    if gap < CLEARANCE:
                        break
                    free = True
                    step = min(gap - CLEARANCE, 0.045 - depth)
                    if step < 2e-4:
                        break
                    depth += step
                if free:
                    while _gap(pieces, bvh, tcp, depth) < CLEARANCE:  # pragma: no cover
                        depth -= 2e-4
                tcp[:3, 3] += depth * z
                base = tcp @ np.linalg.inv(tool_from_base)
                (good if free else bad).append(base)
        if len(good) >= n:
            break
    assert len(good) >= n, f"only {len(good)} grasps"
    return np.array(good[:n]), np.array(bad[: n // 10])


def _write_acronym(path, good, bad, mesh_name):
    with h5py.File(path, "w") as fh:
        fh["grasps/transforms"] = np.concatenate([good, bad])
        fh["grasps/qualities/flex/object_in_gripper"] = np.r_[
            np.ones(len(good)), np.zeros(len(bad))
        ]
        fh["object/file"] = mesh_name
        fh["object/scale"] = 1.0


class Oracle:
    """Independent collision check: unreduced erd Panda (fingers open), table, mug mesh."""

    def __init__(self, whole, mug_pose):
        erd = example_robot_data.load("panda")
        self.model, gm = erd.model, erd.collision_model.copy()  # erd applied the SRDF
        n_rob = gm.ngeoms
        self_pairs = [(int(p.first), int(p.second)) for p in gm.collisionPairs]
        table = pin.GeometryObject(
            "t", 0, 0, pin.SE3(np.eye(3), np.array([0.0, 0.0, -0.025])), coal.Box(2.0, 2.0, 0.05)
        )
        mug = pin.GeometryObject("o", 0, 0, pin.SE3(mug_pose), to_bvh(whole))
        it, io = gm.addGeometryObject(table), gm.addGeometryObject(mug)
        gm.removeAllCollisionPairs()
        link0 = gm.getGeometryId("panda_link0_0")
        for a, b in self_pairs:
            gm.addCollisionPair(pin.CollisionPair(a, b))
        for i in range(n_rob):
            if i != link0:
                gm.addCollisionPair(pin.CollisionPair(i, it))
            gm.addCollisionPair(pin.CollisionPair(i, io))
        # coal's complete answer on every pair (contact information on)
        self.gm, self.gd = gm, complete_answers(pin.GeometryData(gm))
        self.data = self.model.createData()
        self.tcp = self.model.getFrameId("panda_hand_tcp")

    def free(self, q7, target=None):
        """Collision-free, inside the limits and (if given) at the target pose."""
        q = np.concatenate([q7, [0.04, 0.04]])
        m = self.model
        if np.any(q[:7] <= m.lowerPositionLimit[:7]) or np.any(q[:7] >= m.upperPositionLimit[:7]):
            return False
        if target is not None:
            pin.framesForwardKinematics(m, self.data, q)
            pose = self.data.oMf[self.tcp].homogeneous
            rot = np.arccos(np.clip((np.trace(pose[:3, :3].T @ target[:3, :3]) - 1) / 2, -1, 1))
            if np.linalg.norm(pose[:3, 3] - target[:3, 3]) > 1e-4 or rot > 1e-3:
                return False
        return not pin.computeCollisions(m, self.data, self.gm, self.gd, q, True)


def test_acronym_grasps_on_a_thin_walled_mug(tmp_path, panda):
    parts = cup_parts()
    whole = trimesh.util.concatenate(parts)
    whole.export(tmp_path / "mug.stl")
    good, bad = sample_antipodal_grasps(parts, 300, seed=4)
    _write_acronym(tmp_path / "mug_grasps.h5", good, bad, "mug.stl")
    (tmp_path / "mug.yaml").write_text(
        f"""
seed: 0
robot: {{spec: panda}}
object: {{shape: mesh, mesh: mug.stl, pose: {MUG_POSE}}}
candidates:
  source: file
  path: mug_grasps.h5
  format: acronym
  frame: object
  success_only: true
  grasp_to_tool: {{xyz: [0, 0, {BASE_TO_TCP}], rpy_deg: [0, 0, -90]}}
manifold: {{projection: cylindrical}}
"""
    )
    cfg = gcm.load_config(tmp_path / "mug.yaml")
    assert cfg.environment.contact_tolerance == 0.005 and cfg.environment.table is not None
    grasps = gcm.generate_candidates(cfg)
    assert len(grasps) == len(good)  # the failed ones are dropped
    robot = panda
    checked = gcm.check_reachability(grasps, robot, cfg)
    targets = dq_to_matrix(grasps["dq"])  # base frame = world frame here
    mug_pose = cfg.object.pose.matrix()
    oracle = Oracle(whole, mug_pose)

    # truth: any IK candidate (generous seeds, no collision filter) that the oracle accepts
    ref = solve_ik(
        robot,
        targets,
        return_all=True,
        library_seeds=64,
        random_restarts=64,
        min_solutions=16,
        random_seed=1,
    )
    cand = ref.candidates
    truth = np.zeros(len(targets), dtype=bool)
    for i, q in zip(cand.index, cand.q, strict=True):
        if not truth[i] and oracle.free(q, targets[i]):
            truth[i] = True
    reported = np.asarray(checked["reachable"], dtype=bool)
    for i in np.flatnonzero(reported):  # the pipeline's own solutions count as truth too
        truth[i] |= oracle.free(checked["q"][i], targets[i])

    false_pos = [
        i for i in np.flatnonzero(reported) if not oracle.free(checked["q"][i], targets[i])
    ]
    recall = (reported & truth).sum() / truth.sum()
    reasons = dict(
        zip(*np.unique(checked["reason"][truth & ~reported], return_counts=True), strict=True)
    )
    print(
        f"acceptance: {len(good)} grasps, {truth.sum()} reachable in truth, {reported.sum()} "
        f"reported, recall {recall:.4f}, {len(false_pos)} false positives, missed {reasons}"
    )
    assert truth.sum() >= 100, f"only {truth.sum()} truly reachable grasps"
    assert false_pos == [], f"reported reachable but colliding or off target: rows {false_pos}"
    assert recall >= 0.99, f"recall {recall:.3f}; missed by reason {reasons}"
