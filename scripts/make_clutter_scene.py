"""Render a cluttered table scene into Contact-GraspNet's input layout, with grasps of its mug.

Several meshes stand on a table top (the plane z = 0 of the world, the
default ``environment.table``): the ACRONYM mug (the target, segment 1)
placed upright by the same code as ``candidates.placement`` of ``format:
acronym``, ``configs/data/mug.obj`` (segment 2), a box (segment 3) and a
cylinder (segment 4). A virtual pinhole camera (OpenCV convention: x right,
y down, z forward; intrinsics ``K``) sees them; trimesh's ray caster (Embree
when installed, else its pure-Python caster) shoots one ray through every
pixel and records the first hit (pixel (row v, column u) looks along
``((u - cx) / fx, (v - cy) / fy, 1)``, the convention of Contact-GraspNet's
``depth2pc``).

Written into ``--out`` (default ``tests/data/clutter``):

``scene.npz``
    Contact-GraspNet's input layout (``load_available_input_data`` of its
    ``data.py``): ``depth`` (H, W) float32 [m] along the camera's z, 0 where
    the ray hits nothing; ``K`` (3, 3) float64; ``segmap`` (H, W) uint8, the
    segment of the hit (0 = table or nothing); ``rgb`` (H, W, 3) uint8 in BGR
    order as OpenCV reads an image (Contact-GraspNet's loader turns it into
    RGB), a flat colour per segment shaded by the angle of the ray to the
    surface. Depths are rounded to 0.1 mm (like a depth sensor's step).
``scene.ply``
    The same hits as a binary point cloud in the camera frame (xyz float32,
    red/green/blue uchar), every ``--ply-stride``-th pixel of each row and column.
``predictions.npz``
    Contact-GraspNet's prediction layout (``pred_grasps_cam``, ``contact_pts``
    as dicts keyed by segment id, here ``{1: ...}``): up to ``--grasps`` of the
    ACRONYM file's successful grasps of the mug, as Franka-hand base poses in
    the camera frame, and each grasp's contact point: where a ray from the
    -x finger's pad along its closing direction (+x of the hand) first meets
    the mug, tried from the fingertip (z = 0.1034 m) back along the pad; a
    grasp whose rays all miss is left out. Contact-GraspNet's own
    predictions put the contact there too (at x = -width / 2, y = 0,
    z = 0.1034 m in the hand's frame). No ``scores`` (ACRONYM has none).
``scene.json``
    The camera pose (``xyz``, ``rpy_deg`` as a config's ``camera_pose`` takes
    it, and the 4x4 matrix), the image size, and every object's segment,
    name, source, world pose (4x4 and as a config's ``xyz``/``rpy``) and
    the pixels it covers.

Run from the repository root (needs h5py for the ACRONYM file)::

    python scripts/make_clutter_scene.py --out tests/data/clutter
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from gcm_pipeline.config.sections import Pose
from gcm_pipeline.sources.file_object import load_scaled, stable_placement
from gcm_pipeline.sources.files.acronym import read_acronym, read_acronym_object

ROOT = Path(__file__).resolve().parent.parent
ACRONYM = ROOT / "tests/data/acronym/Mug_10f6e09036350e92b3f21f1137c3c347_0.0002682457830986903.h5"
MUG_MESH = ROOT / "tests/data/acronym/10f6e09036350e92b3f21f1137c3c347.obj"
SIMPLE_MUG = ROOT / "configs/data/mug.obj"

#: The camera in the world: a config's ``camera_pose`` (R = Rz(yaw) Ry(pitch) Rx(roll)).
CAMERA_XYZ = (0.95, 0.3, 0.5)
CAMERA_RPY_DEG = (-130.0, 0.0, 120.0)
#: Where the target mug stands (``candidates.placement.xy``).
MUG_XY = (0.5, 0.0)
#: Franka hand (ACRONYM / Contact-GraspNet base frame): fingertip depth and pad length [m].
FINGERTIP_Z = 0.1034
PAD_LENGTH = 0.045
FINGER_X = 0.05

#: One PLY vertex: position [m] and colour.
PLY_VERTEX = [(c, "<f4") for c in "xyz"] + [(c, "u1") for c in ("red", "green", "blue")]

#: Flat colour of each segment (0: table).
COLORS = np.array(
    [[196, 164, 120], [200, 60, 50], [60, 110, 200], [70, 170, 90], [230, 190, 40]],
    dtype=np.float64,
)


def translation(xyz: tuple[float, float, float]) -> np.ndarray:
    """A (4, 4) translation."""
    m = np.eye(4)
    m[:3, 3] = xyz
    return m


def scene_objects() -> list[dict]:
    """The table and the objects: segment, name, source, mesh in its frame, world pose."""
    mug_name, scale = read_acronym_object(ACRONYM)
    mug = load_scaled(MUG_MESH, scale, f"{ACRONYM}: object/file -> {MUG_MESH}")
    placed = stable_placement(mug, MUG_XY, 0.0, 0.0, None, str(MUG_MESH)).pose
    simple = trimesh.load(SIMPLE_MUG, force="mesh")
    box = trimesh.creation.box(extents=(0.06, 0.08, 0.14))
    cyl = trimesh.creation.cylinder(radius=0.035, height=0.16, sections=48)
    table = trimesh.creation.box(extents=(0.7, 0.9, 0.04))
    return [
        dict(segment=0, name="table", source="box 0.7 x 0.9 x 0.04 m, top at z = 0",
             mesh=table, pose=translation((0.55, 0.0, -0.02))),
        dict(segment=1, name="acronym_mug", source=f"{MUG_MESH.name} (ACRONYM {mug_name}), "
             f"scale {scale!r}, upright at xy {list(MUG_XY)}", mesh=mug, pose=placed),
        dict(segment=2, name="mug", source="configs/data/mug.obj", mesh=simple,
             pose=translation((0.58, 0.2, 0.0))),
        dict(segment=3, name="box", source="box 0.06 x 0.08 x 0.14 m", mesh=box,
             pose=translation((0.5, -0.14, 0.07))),
        dict(segment=4, name="cylinder", source="cylinder r 0.035 m, h 0.16 m", mesh=cyl,
             pose=translation((0.66, -0.05, 0.08))),
    ]  # fmt: skip


def config_pose(m: np.ndarray) -> dict:
    """A pose as a config's ``pose`` takes it: ``xyz`` [m] and ``rpy`` [rad]."""
    rpy = Rotation.from_matrix(m[:3, :3]).as_euler("xyz")  # R = Rz(yaw) Ry(pitch) Rx(roll)
    return {"xyz": [round(float(v), 9) for v in m[:3, 3]], "rpy": [float(v) for v in rpy]}


def intrinsics(width: int, height: int, fov_x_deg: float) -> np.ndarray:
    """A pinhole K with square pixels and the principal point at the image centre."""
    f = (width / 2) / math.tan(math.radians(fov_x_deg) / 2)
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def render(objects: list[dict], K: np.ndarray, cam: np.ndarray, width: int, height: int):
    """Ray-cast every pixel centre: depth [m], segment, rgb and the camera-frame hits.

    Returns:
        depth (H, W) float32, segmap (H, W) uint8, rgb (H, W, 3) uint8 (RGB order).
    """
    meshes, seg_of_face = [], []
    for o in objects:
        m = o["mesh"].copy()
        m.apply_transform(o["pose"])
        meshes.append(m)
        seg_of_face.append(np.full(len(m.faces), o["segment"], dtype=np.uint8))
    world = trimesh.util.concatenate(meshes)
    seg_of_face = np.concatenate(seg_of_face)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays_cam = np.stack(
        [(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1
    ).reshape(-1, 3)
    dirs = rays_cam @ cam[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = np.broadcast_to(cam[:3, 3], dirs.shape)
    hits, ray, tri = world.ray.intersects_location(origins, dirs, multiple_hits=False)
    depth = np.zeros(height * width)
    segmap = np.zeros(height * width, dtype=np.uint8)
    rgb = np.zeros((height * width, 3), dtype=np.uint8)
    z_cam = (hits - cam[:3, 3]) @ cam[:3, 2]  # depth along the optical axis
    depth[ray] = np.round(z_cam, 4)
    segmap[ray] = seg_of_face[tri]
    shade = np.abs(np.einsum("ij,ij->i", world.face_normals[tri], dirs[ray]))
    rgb[ray] = np.clip(COLORS[seg_of_face[tri]] * (0.35 + 0.65 * shade[:, None]), 0, 255)
    return (
        depth.reshape(height, width).astype(np.float32),
        segmap.reshape(height, width),
        rgb.reshape(height, width, 3),
    )


def back_project(depth: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (M, 3) of the pixels with a depth, and their (row, col) (M, 2)."""
    rows, cols = np.nonzero(depth > 0)
    z = depth[rows, cols].astype(np.float64)
    x = (cols - K[0, 2]) * z / K[0, 0]
    y = (rows - K[1, 2]) * z / K[1, 1]
    return np.column_stack([x, y, z]), np.column_stack([rows, cols])


def write_ply(path: Path, points: np.ndarray, colors: np.ndarray) -> None:
    """A binary little-endian PLY of xyz float32 and red/green/blue uchar."""
    vertex = np.zeros(len(points), dtype=PLY_VERTEX)
    for k, name in enumerate("xyz"):
        vertex[name] = points[:, k]
    for k, name in enumerate(("red", "green", "blue")):
        vertex[name] = colors[:, k]
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    path.write_bytes(header.encode("ascii") + vertex.tobytes())


def mug_grasps(mug: dict, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """World poses (M, 4, 4) of the mug's successful grasps and their contact points (M, 3)."""
    poses, success, _ = read_acronym(ACRONYM, 10_000)
    poses = poses[np.asarray(success, dtype=bool)]
    mesh = mug["mesh"]
    depths = np.linspace(FINGERTIP_Z, FINGERTIP_Z - PAD_LENGTH, 5)
    contact = np.full((len(poses), 3), np.nan)
    for z in depths:  # from the fingertip back along the pad; first hit wins
        todo = np.flatnonzero(np.isnan(contact[:, 0]))
        if not len(todo):
            break
        origin = poses[todo] @ np.array([-FINGER_X, 0.0, z, 1.0])
        direction = poses[todo][:, :3, 0]
        hits, ray, _ = mesh.ray.intersects_location(origin[:, :3], direction, multiple_hits=False)
        ok = np.linalg.norm(hits - origin[ray, :3], axis=1) <= 2 * FINGER_X
        contact[todo[ray[ok]]] = hits[ok]
    keep = np.flatnonzero(np.isfinite(contact[:, 0]))
    rng = np.random.default_rng(seed)
    keep = np.sort(rng.choice(keep, size=min(count, len(keep)), replace=False))
    world = mug["pose"]
    points = contact[keep] @ world[:3, :3].T + world[:3, 3]
    return world @ poses[keep], points


def bounded(kind: type, low: float, high: float | None = None, *, open_: bool = False):
    """An argparse type: a finite ``kind`` in [low, high] ((low, high) with ``open_``)."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            what = "an integer" if kind is int else "a number"
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None
        inside = low < value if open_ else low <= value
        if high is not None:
            inside = inside and (value < high if open_ else value <= high)
        if not (math.isfinite(value) and inside):
            lo, hi = ("(", ")") if open_ else ("[", "]")
            span = f"in {lo}{low}, {high}{hi}" if high is not None else f">= {low}"
            raise argparse.ArgumentTypeError(f"{text} is not {span}")
        return value

    return parse


def main() -> None:
    """Render the scene and write its files (every argument checked before any work)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "tests/data/clutter")
    parser.add_argument("--width", type=bounded(int, 1, 4096), default=320)
    parser.add_argument("--height", type=bounded(int, 1, 4096), default=240)
    parser.add_argument(
        "--fov",
        type=bounded(float, 0, 180, open_=True),
        default=45.0,
        help="horizontal field of view [deg]",
    )
    parser.add_argument("--ply-stride", type=bounded(int, 1), default=3)
    parser.add_argument("--grasps", type=bounded(int, 1), default=150)
    parser.add_argument("--seed", type=bounded(int, 0, 2**32 - 1), default=0)
    args = parser.parse_args()
    objects = scene_objects()
    cam = Pose(xyz=CAMERA_XYZ, rpy_deg=CAMERA_RPY_DEG).matrix()
    K = intrinsics(args.width, args.height, args.fov)
    depth, segmap, rgb = render(objects, K, cam, args.width, args.height)
    world_poses, contacts = mug_grasps(objects[1], args.grasps, args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    bgr = np.ascontiguousarray(rgb[..., ::-1])  # as cv2.imread gives it
    np.savez_compressed(args.out / "scene.npz", depth=depth, K=K, segmap=segmap, rgb=bgr)
    stride = np.zeros_like(depth, dtype=bool)
    stride[:: args.ply_stride, :: args.ply_stride] = True
    points, pix = back_project(np.where(stride, depth, 0), K)
    write_ply(args.out / "scene.ply", points, rgb[pix[:, 0], pix[:, 1]])
    to_cam = np.linalg.inv(cam)
    pred = to_cam @ world_poses
    pts = contacts @ to_cam[:3, :3].T + to_cam[:3, 3]
    np.savez(
        args.out / "predictions.npz",
        pred_grasps_cam=np.array({1: pred.astype(np.float32)}, dtype=object),
        contact_pts=np.array({1: pts.astype(np.float32)}, dtype=object),
    )
    meta = {
        "command": "python scripts/make_clutter_scene.py "
        + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items() if k != "out"),
        "camera_pose": {"xyz": list(CAMERA_XYZ), "rpy_deg": list(CAMERA_RPY_DEG)},
        "camera_matrix": np.round(cam, 12).tolist(),
        "image": {"width": args.width, "height": args.height, "fov_x_deg": args.fov},
        "objects": [
            {
                "segment": o["segment"],
                "name": o["name"],
                "source": o["source"],
                "pose": np.round(o["pose"], 12).tolist(),
                "config_pose": config_pose(o["pose"]),
                "pixels": int(np.count_nonzero(segmap[depth > 0] == o["segment"])),
            }
            for o in objects
        ],
        "grasps": len(pred),
    }
    (args.out / "scene.json").write_text(json.dumps(meta, indent=1) + "\n")
    hit = int(np.count_nonzero(depth > 0))
    print(
        f"{args.out}: {args.width}x{args.height}, {hit} pixels hit, {len(points)} ply points, "
        f"{len(pred)} grasps of the mug"
    )


if __name__ == "__main__":
    main()
