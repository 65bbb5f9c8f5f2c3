"""Importers of synthesisers' grasp files and the gripper registry.

Every test writes a small file the way the format's documentation describes
it (not with our own mapping) and checks the imported grasp frame against a
hand-computed one: a grasp approaching the top face of a box from above ends
with the TCP at the face centre, z pointing down, fingers closing along the
world y axis.
"""

from __future__ import annotations

import io
import json
import pickle
import zipfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import DATA, assert_one_line_error
from scipy.spatial.transform import Rotation

from gcm_pipeline.cli import main
from gcm_pipeline.config import Config
from gcm_pipeline.config.gripper_spec import load_gripper
from gcm_pipeline.errors import ConfigError, InputError
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.pipeline import generate_candidates
from gcm_pipeline.sources.files import read_contact_graspnet, read_grasp_file, read_grasps

BOX_SIZE = (0.10, 0.06, 0.10)
BOX_XYZ = (0.5, 0.0, 0.05)  # the box stands on the table: top face at z = 0.10
TOP = np.array([0.5, 0.0, 0.10])
APPROACH = np.array([0.0, 0.0, -1.0])
CLOSING = np.array([0.0, 1.0, 0.0])


def expected_tool() -> np.ndarray:
    """The robot's grasp frame (panda_hand_tcp) of the top grasp, by hand."""
    t = np.eye(4)
    t[:3, 0] = np.cross(CLOSING, APPROACH)  # x = y x z = (-1, 0, 0)
    t[:3, 1] = CLOSING
    t[:3, 2] = APPROACH
    t[:3, 3] = TOP
    return t


def config(candidates: dict, **extra) -> Config:
    return Config.from_dict(
        {
            "object": {"shape": "box", "dims": {"size": list(BOX_SIZE)}, "pose": {"xyz": BOX_XYZ}},
            "candidates": {"source": "file", **candidates},
            **extra,
        }
    )


def imported(cfg: Config):
    table = generate_candidates(cfg)
    return dq_to_matrix(table["dq"]), table


def assert_pose(m: np.ndarray, want: np.ndarray) -> None:
    np.testing.assert_allclose(m[:3, 3], want[:3, 3], atol=1e-6)
    np.testing.assert_allclose(m[:3, :3], want[:3, :3], atol=1e-6)


# ------------------------------------------------------------------ grippers


def test_registry_base_convention_is_the_acronym_grasp_to_tool():
    g = load_gripper("franka_panda")
    # the README's hand-written map for ACRONYM files
    want = config(
        {"path": "x.npy", "grasp_to_tool": {"xyz": [0, 0, 0.1034], "rpy_deg": [0, 0, -90]}}
    ).candidates.grasp_to_tool.matrix()
    np.testing.assert_allclose(g.to_tool("base"), want, atol=1e-12)
    assert g.max_width == 0.08 and 0 < g.finger_depth < 0.06


def test_registry_unknown_gripper_lists_the_known_ones():
    with pytest.raises(ConfigError, match="unknown gripper 'robotiq'.*valid: franka_panda"):
        load_gripper("robotiq")
    with pytest.raises(ConfigError, match="candidates.*unknown gripper 'panda_hand'.*franka_panda"):
        config({"path": "g.json", "gripper": "panda_hand"})


# ------------------------------------------------------------------ GraspGen


def graspgen_base_in_object() -> np.ndarray:
    """GraspGen/ACRONYM base-link frame of the top grasp in the box frame (docs: z approach,
    fingers closing along x, TCP 0.1034 m along z)."""
    t = np.eye(4)
    t[:3, 0] = CLOSING
    t[:3, 2] = APPROACH
    t[:3, 1] = np.cross(APPROACH, CLOSING)
    t[:3, 3] = (TOP - BOX_XYZ) - 0.1034 * APPROACH
    return t


def test_graspgen_json_dataset_layout(tmp_path):
    base = graspgen_base_in_object()
    other = base.copy()
    other[0, 3] += 0.02
    path = tmp_path / "box_grasps.json"
    path.write_text(
        json.dumps(
            {
                "object": {"file": "meshes/box.obj", "scale": 1.0},
                "grasps": {
                    "transforms": [base.tolist(), other.tolist()],
                    "object_in_gripper": [True, False],
                    "confidences": [0.9, 0.4],
                },
            }
        )
    )
    every = {"path": str(path), "frame": "object", "gripper": "franka_panda", "success_only": False}
    cfg = config(every)
    assert cfg.candidates.format == "graspgen"  # from the suffix
    poses, table = imported(cfg)
    assert_pose(poses[0], expected_tool())
    np.testing.assert_allclose(poses[1][:3, 3], TOP + [0.02, 0, 0], atol=1e-9)
    np.testing.assert_array_equal(table["score"], [0.9, 0.4])
    np.testing.assert_array_equal(table["source_id"], [0, 1])
    only = config(
        {"path": str(path), "frame": "object", "success_only": True, "gripper": "franka_panda"}
    )
    poses, table = imported(only)
    assert len(poses) == 1 and table["score"].tolist() == [0.9]
    # by default a file with success labels keeps the successful grasps only
    poses, table = imported(config({k: v for k, v in every.items() if k != "success_only"}))
    assert len(poses) == 1 and table["source_id"].tolist() == [0]


@pytest.mark.parametrize(
    "name, count, depth",
    [
        ("ginger_grasps.yml", 50, 0.068),  # GraspGenX, openarm gripper
        ("example_mesh_antipodal.yaml", 40, 0.195),  # GraspGen, Robotiq 2F-140
        ("example_pointcloud_collisionfree_antipodal.yaml", 18, 0.195),
    ],
)
def test_graspgen_isaac_grasp_yaml_real_inference_output(name, count, depth):
    """Public GraspGen(X) output (tests/data/graspgen/README.md): every pose and confidence
    in file order, the fingertips ``depth`` along the base frame's +z."""
    path = DATA / "graspgen" / name
    grasps = yaml.safe_load(path.read_text())["grasps"]
    got = read_grasps(path, "graspgen")
    assert got.convention == "base" and got.gripper is None  # the file names no gripper
    assert len(got.poses) == len(grasps) == count
    for m, (name, g) in zip(got.poses, grasps.items(), strict=True):
        q = [*g["orientation"]["xyz"], g["orientation"]["w"]]
        np.testing.assert_allclose(m[:3, 3], g["position"], atol=1e-12, err_msg=name)
        np.testing.assert_allclose(m[:3, :3], Rotation.from_quat(q).as_matrix(), atol=1e-9)
    np.testing.assert_allclose(got.columns["score"], [g["confidence"] for g in grasps.values()])
    # read as a user would, with the gripper's fingertip offset
    poses, table = imported(
        config({"path": str(path), "frame": "object", "grasp_to_tool": {"xyz": [0, 0, depth]}})
    )
    tips = got.poses[:, :3, 3] + depth * got.poses[:, :3, 2]
    np.testing.assert_allclose(poses[:, :3, 3] - np.array(BOX_XYZ), tips, atol=1e-9)
    assert table["score"].max() == pytest.approx(max(g["confidence"] for g in grasps.values()))


def test_graspgen_isaac_grasp_yaml(tmp_path):
    base = graspgen_base_in_object()
    q = Rotation.from_matrix(base[:3, :3]).as_quat()  # x, y, z, w
    doc = {
        "format": "isaac_grasp",
        "format_version": 1.0,
        "grasps": {
            "grasp_0": {
                "confidence": 0.75,
                "position": base[:3, 3].tolist(),
                "orientation": {"w": float(q[3]), "xyz": q[:3].tolist()},
            }
        },
    }
    path = tmp_path / "box_grasps.yml"
    path.write_text(yaml.safe_dump(doc))
    poses, table = imported(
        config({"path": str(path), "frame": "object", "gripper": "franka_panda"})
    )
    assert_pose(poses[0], expected_tool())
    assert table["score"].tolist() == [0.75]


# ---------------------------------------------------------- Contact-GraspNet

# camera 0.7 m above the box top looking straight down (OpenCV optical frame:
# z forward = world -z, x right = world +x, y down = world -y)
CAM = np.eye(4)
CAM[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]
CAM[:3, 3] = [0.5, 0.0, 0.8]


def cgn_grasp(width: float) -> np.ndarray:
    """Contact-GraspNet's build_6d_grasp in the camera frame: R = [b, a x b, a],
    t = contact + width / 2 * b - 0.1034 * a."""
    r_cam = CAM[:3, :3].T
    a, b = r_cam @ APPROACH, r_cam @ CLOSING
    top_cam = r_cam @ (TOP - CAM[:3, 3])
    contact = top_cam - width / 2 * b  # one finger's contact, level with the fingertips
    t = np.eye(4)
    t[:3, :3] = np.column_stack([b, np.cross(a, b), a])
    t[:3, 3] = contact + width / 2 * b - 0.1034 * a
    return t


def test_contact_graspnet_npz_in_the_camera_frame(tmp_path):
    g = cgn_grasp(0.06)
    path = tmp_path / "predictions_scene.npz"
    # as inference.py saves them: dicts keyed by segment id (pickled object arrays)
    np.savez(
        path,
        pred_grasps_cam={3: np.stack([g, g]).astype(np.float32), 1: g[None]},
        scores={3: np.array([0.2, 0.8], np.float32), 1: np.array([0.5], np.float32)},
        contact_pts={3: np.zeros((2, 3)), 1: np.zeros((1, 3))},
        gripper_openings={3: np.array([0.06, 0.05]), 1: np.array([0.04])},
    )
    cam = {"xyz": CAM[:3, 3].tolist(), "rpy_deg": [180, 0, 0]}
    cfg = config({"path": str(path), "format": "contact_graspnet", "camera_pose": cam})
    poses, table = imported(cfg)
    for m in poses:
        assert_pose(m, expected_tool())  # float32 in the file: 1e-6 is enough
    assert table["segment"].tolist() == [1, 3, 3]  # segments in ascending order
    np.testing.assert_allclose(table["score"], [0.5, 0.2, 0.8], rtol=1e-6)
    np.testing.assert_allclose(table["width"], [0.04, 0.06, 0.05])
    assert table["source_id"].tolist() == [0, 0, 1]


def test_contact_graspnet_float_segment_keys_and_an_empty_segment(tmp_path):
    """The layout of public predictions (github.com/FrankJIE09/contact_graspnet results/):
    segment ids saved as np.float32 keys, a segment with no grasps, no gripper_openings."""
    g = cgn_grasp(0.06).astype(np.float32)
    path = tmp_path / "predictions_7.npz"
    np.savez(
        path,
        pred_grasps_cam={
            np.float32(2.0): np.stack([g, g]),
            np.float32(8.0): np.zeros((0, 4, 4), np.float32),
            np.float32(10.0): g[None],
        },
        scores={
            np.float32(2.0): np.array([0.3, 0.6], np.float32),
            np.float32(8.0): np.zeros(0, np.float32),
            np.float32(10.0): np.array([0.9], np.float32),
        },
        contact_pts={
            np.float32(2.0): np.zeros((2, 3), np.float32),
            np.float32(8.0): np.zeros((0, 3), np.float32),
            np.float32(10.0): np.zeros((1, 3), np.float32),
        },
    )
    cam = {"xyz": CAM[:3, 3].tolist(), "rpy_deg": [180, 0, 0]}
    poses, table = imported(
        config({"path": str(path), "format": "contact_graspnet", "camera_pose": cam})
    )
    assert len(poses) == 3  # the empty segment adds no row
    for m in poses:
        assert_pose(m, expected_tool())
    assert table["segment"].tolist() == [2, 2, 10]  # numeric order, not "10" < "2"
    np.testing.assert_allclose(table["score"], [0.3, 0.6, 0.9], rtol=1e-6)
    assert np.isnan(table["width"]).all()


def test_contact_graspnet_needs_a_camera_pose():
    with pytest.raises(ConfigError, match="candidates: .camera_pose. is missing.*camera frame"):
        config({"path": "p.npz", "format": "contact_graspnet"})


def test_contact_graspnet_never_runs_pickled_code(tmp_path):
    class Evil:
        def __reduce__(self):
            return (Path.touch, (tmp_path / "pwned",))

    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.array(Evil(), dtype=object), allow_pickle=True)
    path = tmp_path / "evil.npz"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("pred_grasps_cam.npy", buf.getvalue())
    with pytest.raises(InputError, match="refusing to load"):
        read_contact_graspnet(path)
    assert not (tmp_path / "pwned").exists()
    assert pickle  # the stdlib module the attack would need is not what we use to read


def _object_npz(path: Path, **members: object) -> Path:
    """An ``.npz`` whose members are pickled object arrays (as Contact-GraspNet saves dicts)."""
    with zipfile.ZipFile(path, "w") as zf:
        for name, value in members.items():
            buf = io.BytesIO()
            arr = np.empty((), dtype=object)
            arr[()] = value
            np.lib.format.write_array(buf, arr, allow_pickle=True)
            zf.writestr(f"{name}.npy", buf.getvalue())
    return path


def test_contact_graspnet_pickle_that_expands_is_refused_before_it_is_built(tmp_path):
    """A pickle refers to one list many times for 2 bytes each: sized by what it expands to."""
    pose = np.eye(4).tolist()
    shared = [pose] * 1000  # one list of 1,000 poses ...
    path = _object_npz(tmp_path / "bomb.npz", pred_grasps_cam={0: [shared] * 20_000})  # 20M poses
    assert path.stat().st_size < 200_000
    with pytest.raises(
        InputError, match=r"array 'pred_grasps_cam' expands to more than 64,131,072"
    ):
        read_contact_graspnet(path)
    # nested without end
    deep: list = [[1.0]]
    for _ in range(50):
        deep = [deep]
    path = _object_npz(tmp_path / "deep.npz", pred_grasps_cam={0: deep})
    with pytest.raises(InputError, match="nests lists or dicts more than 8 levels deep"):
        read_contact_graspnet(path)
    # a pickle of DUP opcodes: 1 byte each, a reference each, before anything can be counted
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "|O", "fortran_order": False, "shape": ()}
    )
    dups = header.getvalue() + b"\x80\x02N" + b"2" * 5_000_000 + b"."
    _npz_member(tmp_path / "dup.npz", "pred_grasps_cam", dups)
    with pytest.raises(InputError, match="its pickle takes more than 1,000,000 steps"):
        read_contact_graspnet(tmp_path / "dup.npz")
    # a chain of shared lists nested deeper than 8 (each object once in a memo by id)
    chain: list = [[1.0]]
    for _ in range(20):
        chain = [chain, chain]
    path = _object_npz(tmp_path / "chain.npz", pred_grasps_cam={0: chain})
    with pytest.raises(InputError, match="more than 8 levels deep"):
        read_contact_graspnet(path)
    # ragged lists: one line
    path = _object_npz(tmp_path / "ragged.npz", pred_grasps_cam={0: [[1, 2], [3]]})
    with pytest.raises(InputError, match=r"must map segments to \(M, 4, 4\) arrays"):
        read_contact_graspnet(path)
    # the layout Contact-GraspNet writes (dicts of arrays) reads, scores as a list too
    path = _object_npz(
        tmp_path / "ok.npz", pred_grasps_cam={3: np.stack([pose, pose])}, scores={3: [0.5, 0.25]}
    )
    got = read_contact_graspnet(path)
    assert got.poses.shape == (2, 4, 4) and got.columns["score"].tolist() == [0.5, 0.25]
    assert got.columns["segment"].tolist() == [3, 3]


# ------------------------------------------------------------------ GraspNet


def graspnet_row(
    depth: float = 0.02, score: float = 0.7, object_id: int = 3, tips: np.ndarray | None = None
) -> np.ndarray:
    """graspnetAPI's row [score, width, height, depth, R(9), t(3), object_id]: x approach,
    y closing, fingertips ``depth`` past the centre along x. By default the fingertips are
    where the Panda's are when its TCP is at the top face (8.9 mm past it, see
    test_panda_fingertips_are_finger_tip_past_the_tcp)."""
    if tips is None:
        tips = TOP + load_gripper("franka_panda").finger_tip * APPROACH
    r = np.column_stack([APPROACH, CLOSING, np.cross(APPROACH, CLOSING)])
    center = tips - depth * APPROACH
    return np.r_[score, 0.06, 0.02, depth, r.reshape(-1), center, object_id]


def test_graspnet_rows(tmp_path):
    rows = np.stack([graspnet_row(0.02), graspnet_row(0.03, 0.4, 5)]).astype(np.float32)
    path = tmp_path / "gg.npy"
    np.save(path, rows)  # GraspGroup.save_npy writes the float32 array
    poses, table = imported(config({"path": str(path), "format": "graspnet"}))
    for m in poses:
        assert_pose(m, expected_tool())
    np.testing.assert_allclose(table["score"], [0.7, 0.4], rtol=1e-6)
    np.testing.assert_allclose(table["width"], [0.06, 0.06], rtol=1e-6)
    assert table["object_id"].tolist() == [3, 5]


def test_graspnet_with_a_camera_pose(tmp_path):
    row = graspnet_row()
    r, t = row[4:13].reshape(3, 3), row[13:16]
    row[4:13] = (CAM[:3, :3].T @ r).reshape(-1)
    row[13:16] = CAM[:3, :3].T @ (t - CAM[:3, 3])
    path = tmp_path / "gg.npy"
    np.save(path, row[None])
    cam = {"xyz": CAM[:3, 3].tolist(), "rpy_deg": [180, 0, 0]}
    poses, _ = imported(config({"path": str(path), "format": "graspnet", "camera_pose": cam}))
    assert_pose(poses[0], expected_tool())


# ----------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("fmt", "content", "message"),
    [
        ("graspnet", np.tile(np.eye(4), (2, 1, 1)), r"expected GraspNet rows \(N, 17\)"),
        ("contact_graspnet", {"transforms": np.tile(np.eye(4), (2, 1, 1))}, "pred_grasps_cam"),
        ("graspgen", {"grasps": [1, 2]}, "not a GraspGen grasp file"),
    ],
)
def test_wrong_format_is_one_clear_error(tmp_path, fmt, content, message):
    if fmt == "graspnet":
        path = tmp_path / "g.npy"
        np.save(path, content)
    elif fmt == "contact_graspnet":
        path = tmp_path / "g.npz"
        np.savez(path, **content)
    else:
        path = tmp_path / "g.json"
        path.write_text(json.dumps(content))
    cam = {"camera_pose": {"xyz": [0, 0, 1]}} if fmt == "contact_graspnet" else {}
    with pytest.raises(InputError, match=message):
        generate_candidates(config({"path": str(path), "format": fmt, **cam}))


def test_non_rigid_rotation_names_the_row(tmp_path):
    rows = np.stack([graspnet_row(), graspnet_row()])
    rows[1, 4] = 2.0
    path = tmp_path / "g.npy"
    np.save(path, rows)
    with pytest.raises(InputError, match="grasp 1 .* not a rigid transform"):
        generate_candidates(config({"path": str(path), "format": "graspnet"}))


def test_cli_bad_input_exits_2_and_writes_nothing(tmp_path, capsys):
    bad = tmp_path / "g.npy"
    np.save(bad, np.tile(np.eye(4), (3, 1, 1)))
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        yaml.safe_dump(
            {
                "object": {"shape": "box", "dims": {"size": list(BOX_SIZE)}},
                "candidates": {"source": "file", "path": str(bad), "format": "graspnet"},
                "publish": {"html": False, "plots": False},
            }
        )
    )
    out = tmp_path / "run"
    code = main(["run", str(cfg), "--out", str(out), "--quiet"])
    assert_one_line_error(code, capsys.readouterr().err, "(N, 17)")
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["c.yaml", "g.npy"]


def test_gripper_with_plain_pose_formats_is_rejected():
    with pytest.raises(ConfigError, match="'gripper' needs a format with a documented"):
        config({"path": "g.npy", "format": "npy", "gripper": "franka_panda"})
    with pytest.raises(ConfigError, match="'gripper' or 'grasp_to_tool', not both"):
        config({"path": "g.json", "gripper": "franka_panda", "grasp_to_tool": {"xyz": [0, 0, 0.1]}})


# ------------------------------------------------- GraspNet fingertips (frame)


def test_graspnet_fingertips_land_where_graspnet_draws_them(tmp_path):
    """graspnetAPI draws the fingers over x in [-0.024, depth]: the tips are ``depth`` past
    the centre. The Panda's fingertips are ``finger_tip`` past its TCP (example-robot-data's
    finger meshes end 8.9 mm past panda_hand_tcp), so the TCP sits ``depth - finger_tip``
    past the centre and the real fingertips touch the face, not 9 mm below it."""
    g = load_gripper("franka_panda")
    assert 0.008 < g.finger_tip < 0.010
    path = tmp_path / "gg.npy"
    np.save(path, np.stack([graspnet_row(0.01, tips=TOP), graspnet_row(0.04, tips=TOP)]))
    poses, _ = imported(config({"path": str(path), "format": "graspnet"}))
    for m in poses:
        tips = m[:3, 3] + g.finger_tip * m[:3, 2]
        np.testing.assert_allclose(tips, TOP, atol=1e-9)
        np.testing.assert_allclose(m[:3, 2], APPROACH, atol=1e-9)


def test_panda_fingertips_are_finger_tip_past_the_tcp(panda):
    """The registry's finger_tip is the example-robot-data Panda's own finger length past
    panda_hand_tcp (the visual finger meshes, fingers open)."""
    import pinocchio as pin
    import trimesh

    robot = panda
    model = robot.model
    visual = robot.build_geometry("visual")
    data = model.createData()
    q = pin.neutral(model)
    pin.forwardKinematics(model, data, q)
    pin.updateFramePlacements(model, data)
    gdata = pin.GeometryData(visual)
    pin.updateGeometryPlacements(model, data, visual, gdata)
    tcp = data.oMf[model.getFrameId("panda_hand_tcp")]
    tips = []
    for i, obj in enumerate(visual.geometryObjects):
        if "finger" not in obj.name or not obj.meshPath:
            continue
        v = trimesh.load(obj.meshPath, force="mesh").vertices * np.asarray(obj.meshScale)
        w = v @ gdata.oMg[i].rotation.T + gdata.oMg[i].translation
        tips.append(((w - tcp.translation) @ tcp.rotation)[:, 2].max())
    assert tips
    np.testing.assert_allclose(max(tips), load_gripper("franka_panda").finger_tip, atol=5e-4)


# ------------------------------------------- hostile files: one line, no crash


def _npy_with_header(path: Path, shape: tuple, payload: bytes, descr: str = "<f8") -> None:
    with path.open("wb") as fh:
        header = {"descr": descr, "fortran_order": False, "shape": shape}
        np.lib.format.write_array_header_1_0(fh, header)
        fh.write(payload)


def _npz_member(path: Path, name: str, data: bytes, mode: str = "w") -> None:
    with zipfile.ZipFile(path, mode, compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr(f"{name}.npy", data)


def _pickled_member(obj: object) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "|O", "fortran_order": False, "shape": ()})
    pickle.dump(obj, buf, protocol=4)
    return buf.getvalue()


class _HugeReconstruct:
    """NumPy's own pickled-array constructor (allowed) asked for a 10**14-byte array."""

    def __reduce__(self):
        return (np.zeros(1).__reduce__()[0], (np.ndarray, (10**14,), b"b"))


def _hostile_files(tmp_path: Path) -> list[tuple[str, Path, dict, str]]:
    """(format, file, extra config, expected message) for files that must fail in one line."""
    row = graspnet_row()
    cases = []
    # graspnet: a header that promises 10^9 rows in a few bytes, an empty file, truncated data
    p = tmp_path / "lying.npy"
    _npy_with_header(p, (10**9, 17), row.tobytes())
    cases.append(("graspnet", p, {}, "truncated or corrupt"))
    p = tmp_path / "zero.npy"
    p.write_bytes(b"")
    cases.append(("graspnet", p, {}, "not a .npy array"))
    p = tmp_path / "json.npy"
    p.write_text('{"grasps": []}')
    cases.append(("graspnet", p, {}, "but this is JSON text; use format: graspgen"))
    p = tmp_path / "rows.npy"
    np.save(p, np.tile(row, (50, 1)))
    cases.append(("graspnet", p, {"max_count": 10}, "holds 50 grasps, more than candidates.max"))
    p = tmp_path / "id.npy"
    bad_id = row.copy()
    bad_id[16] = 1e30
    np.save(p, bad_id[None])
    cases.append(("graspnet", p, {}, "row 0 .*object_id"))
    # contact_graspnet: a lying plain header, a deflated bomb, odd values, huge pickled arrays
    cam = {"camera_pose": {"xyz": [0, 0, 1]}}
    p = tmp_path / "lying.npz"
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": "<f8", "fortran_order": False, "shape": (10**9, 4, 4)}
    )
    _npz_member(p, "pred_grasps_cam", buf.getvalue() + np.eye(4).tobytes())
    cases.append(("contact_graspnet", p, cam, "truncated or corrupt"))
    p = tmp_path / "bomb.npz"
    _npz_member(p, "pred_grasps_cam", _pickled_member({0: np.zeros((200_000, 4, 4))}))
    cases.append(("contact_graspnet", p, {**cam, "max_count": 100}, "candidates.max_count"))
    p = tmp_path / "many.npz"
    np.savez(p, pred_grasps_cam={0: np.tile(np.eye(4), (50, 1, 1))})
    cases.append(("contact_graspnet", p, {**cam, "max_count": 10}, "holds 50 grasps"))
    for name, value in [
        ("shape", {0: np.zeros((5, 3))}),
        ("dict", {0: {"x": 1}}),
        ("text", {0: "hello"}),
        ("flat", np.array([1, 2, 3], dtype=object)),
    ]:
        p = tmp_path / f"odd_{name}.npz"
        np.savez(p, pred_grasps_cam=value)
        cases.append(("contact_graspnet", p, cam, r"pred_grasps_cam.* \(M, 4, 4\)"))
    p = tmp_path / "bigkey.npz"
    np.savez(p, pred_grasps_cam={1e300: np.eye(4)[None]})
    cases.append(("contact_graspnet", p, cam, "segment"))
    p = tmp_path / "recon.npz"
    _npz_member(p, "pred_grasps_cam", _pickled_member({0: _HugeReconstruct()}))
    cases.append(("contact_graspnet", p, cam, "refusing"))
    # graspgen: an alias bomb, more grasps than max_count, a file larger than they can take
    p = tmp_path / "bomb.yaml"
    levels = ["a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"] + [
        f"{k}: &{k} [{', '.join(['*' + prev] * 10)}]"
        for prev, k in zip("abcdefg", "bcdefgh", strict=True)
    ]
    p.write_text("\n".join(levels) + "\ngrasps: {transforms: *h}\n")
    cases.append(("graspgen", p, {}, "aliases"))
    p = tmp_path / "many.json"
    p.write_text(json.dumps({"grasps": {"transforms": [np.eye(4).tolist()] * 50}}))
    cases.append(("graspgen", p, {"max_count": 10}, "holds 50 grasps"))
    p = tmp_path / "big.json"
    p.write_text(
        json.dumps({"grasps": {"transforms": [np.eye(4).tolist()]}, "pad": "x" * 3_000_000})
    )
    cases.append(("graspgen", p, {"max_count": 1}, "bytes"))
    p = tmp_path / "deep.json"
    p.write_text("[" * 20_000 + "]" * 20_000)
    cases.append(("graspgen", p, {}, "nested too deeply"))
    p = tmp_path / "empties.json"  # 3 bytes of text, a list of 56 bytes parsed: 20x
    p.write_text("[" + "[]," * 300_000 + "[]]")
    cases.append(("graspgen", p, {"max_count": 10}, "holds about 600,003 JSON values"))
    p = tmp_path / "isaac.yaml"
    p.write_text(
        "format: isaac_grasp\ngrasps:\n  g0: {confidence: 1.0, position: [0, 0, .inf],"
        " orientation: {w: 1, xyz: [0, 0, 0]}}\n"
    )
    cases.append(("graspgen", p, {}, "grasp 'g0': position"))
    return cases


def test_hostile_grasp_files_are_one_line_errors(tmp_path):
    for fmt, path, extra, message in _hostile_files(tmp_path):
        with pytest.raises(InputError, match=message) as info:
            generate_candidates(config({"path": str(path), "format": fmt, **extra}))
        assert "\n" not in str(info.value), (path.name, str(info.value))
        assert str(path) in str(info.value), (path.name, str(info.value))


def test_camera_pose_and_object_frame_are_not_both_taken():
    """With both, the object frame was silently ignored."""
    with pytest.raises(ConfigError, match="'camera_pose'.*or 'frame: object', not both"):
        config(
            {
                "path": "g.npy",
                "format": "graspnet",
                "camera_pose": {"xyz": [0, 0, 1]},
                "frame": "object",
            }
        )


# ------------------------------------------------ no silent guess: dataset grippers

ACRONYM = DATA / "acronym"
#: ACRONYM's example grasps of a mug (NVlabs/acronym, data/examples; MIT, see ACRONYM/README.md)
MUG_H5 = ACRONYM / "Mug_10f6e09036350e92b3f21f1137c3c347_0.0002682457830986903.h5"
MUG_OBJ = ACRONYM / "10f6e09036350e92b3f21f1137c3c347.obj"
MUG_SCALE = 0.0002682457830986903
#: The README's hand-written map of ACRONYM's Franka frame onto panda_hand_tcp
ACRONYM_TO_TCP = {"xyz": [0, 0, 0.1034], "rpy_deg": [0, 0, -90]}


def mug_config(**candidates) -> Config:
    """ACRONYM's mug standing on the table 0.5 m in front of the Panda."""
    return Config.from_dict(
        {
            "object": {
                "shape": "mesh",
                "mesh": str(MUG_OBJ),
                "scale": MUG_SCALE,
                "pose": {"xyz": [0.5, 0.0, -0.0514]},  # the mesh's bottom at z = 0.0514 m
            },
            "candidates": {
                "source": "file",
                "path": str(MUG_H5),
                "frame": "object",
                "success_only": True,
                **candidates,
            },
            "manifold": {"projection": "spherical", "max_edge_length": 0.04},
            "densify": {"subdivisions": 1},
            "publish": {"html": False, "plots": False},
        }
    )


def test_acronym_without_gripper_uses_the_dataset_gripper_and_says_so():
    """The real ACRONYM file names gripper/type 'panda': the registry's Franka hand.

    Without it the hand base was taken for the TCP (10 cm short of the fingertips).
    """
    pytest.importorskip("h5py")
    report: dict = {}
    default = generate_candidates(mug_config(format="acronym"), report=report)
    assert report["grasp_frame"] == {
        "format": "acronym",
        "gripper": "franka_panda",
        "chosen_by": "file",
        "file_gripper": "panda",
        "describe": "franka_panda (named by the file)",
    }
    by_hand = generate_candidates(mug_config(format="acronym", grasp_to_tool=ACRONYM_TO_TCP))
    named = generate_candidates(mug_config(format="acronym", gripper="franka_panda"))
    suffix = generate_candidates(mug_config())  # format from the .h5 suffix
    a, b = dq_to_matrix(default["dq"]), dq_to_matrix(by_hand["dq"])
    assert len(a) == 1290  # ACRONYM's successful grasps of this mug
    np.testing.assert_allclose(a, b, atol=1e-9)
    np.testing.assert_array_equal(default["dq"], named["dq"])
    np.testing.assert_array_equal(default["dq"], suffix["dq"])
    # the file's hand base frames are 0.1034 m behind the TCP along the approach
    from gcm_pipeline.sources.files import read_grasp_file

    base, _ = read_grasp_file(MUG_H5, success_only=True)
    obj = mug_config().object.pose.matrix()
    np.testing.assert_allclose(
        a[:, :3, 3], (obj @ base)[:, :3, 3] + 0.1034 * a[:, :3, 2], atol=1e-9
    )


def _acronym_file(path: Path, gripper: str | None) -> Path:
    h5py = pytest.importorskip("h5py")
    with h5py.File(path, "w") as f:
        f["grasps/transforms"] = np.tile(graspgen_base_in_object(), (2, 1, 1))
        f["grasps/qualities/flex/object_in_gripper"] = np.array([1, 1])
        if gripper is not None:
            f["gripper/type"] = gripper
    return path


def test_a_file_without_gripper_name_gets_its_dataset_gripper(tmp_path):
    report: dict = {}
    path = _acronym_file(tmp_path / "g.h5", None)
    poses, _ = imported_report(config({"path": str(path), "frame": "object"}), report)
    assert_pose(poses[0], expected_tool())
    assert report["grasp_frame"]["chosen_by"] == "dataset"
    assert report["grasp_frame"]["describe"] == "franka_panda (the acronym dataset's gripper)"


def imported_report(cfg: Config, report: dict):
    table = generate_candidates(cfg, report=report)
    return dq_to_matrix(table["dq"]), table


def test_a_file_whose_gripper_is_unknown_is_refused_with_the_choices(tmp_path):
    path = _acronym_file(tmp_path / "g.h5", "barrett_bh8")
    with pytest.raises(InputError) as info:
        generate_candidates(config({"path": str(path), "frame": "object"}))
    msg = str(info.value)
    assert "'barrett_bh8'" in msg and "known: franka_panda" in msg and "grasp_to_tool" in msg
    assert info.value.value == "barrett_bh8"
    registry = ("franka_panda", "robotiq_2f_140", "robotiq_2f_85", "single_suction_cup_30mm")
    assert info.value.choices == (*registry, "grasp_to_tool")
    assert str(path) in msg and "\n" not in msg
    # an explicit map is the way out, and is reported
    report: dict = {}
    generate_candidates(
        config({"path": str(path), "frame": "object", "grasp_to_tool": ACRONYM_TO_TCP}),
        report=report,
    )
    assert report["grasp_frame"]["chosen_by"] == "grasp_to_tool"
    assert report["grasp_frame"]["file_gripper"] == "barrett_bh8"


@pytest.mark.parametrize(
    ("named", "outcome"),
    [
        (None, "refused"),
        ("franka_panda", "file"),
        ({"name": "robotiq_2f_140"}, "robotiq"),
        ({"name": "barrett_bh8"}, "unknown"),
    ],
)
def test_graspgen_grippers(tmp_path, named, outcome):
    """GraspGen publishes grasps for several grippers: its file must say which, or the config."""
    doc = {"grasps": {"transforms": [graspgen_base_in_object().tolist()]}}
    if named is not None:
        doc["gripper"] = named
    path = tmp_path / "g.json"
    path.write_text(json.dumps(doc))
    cfg = config({"path": str(path), "frame": "object"})
    report: dict = {}
    if outcome == "file":
        poses, _ = imported_report(cfg, report)
        assert_pose(poses[0], expected_tool())
        assert report["grasp_frame"]["chosen_by"] == "file"
        return
    if outcome == "robotiq":  # the registry's 2F-140: TCP 0.195 m out (GraspGen's depth)
        poses, _ = imported_report(cfg, report)
        base = graspgen_base_in_object()
        base[:3, 3] += BOX_XYZ  # the object's pose: a translation
        np.testing.assert_allclose(poses[0][:3, 3], base[:3, 3] + 0.195 * base[:3, 2], atol=1e-9)
        np.testing.assert_allclose(poses[0][:3, 1], base[:3, 0], atol=1e-9)  # closing: base x
        np.testing.assert_allclose(poses[0][:3, 2], base[:3, 2], atol=1e-9)  # approach: base z
        assert report["grasp_frame"] == report["grasp_frame"] | {
            "gripper": "robotiq_2f_140",
            "chosen_by": "file",
        }
        return
    with pytest.raises(InputError) as info:
        generate_candidates(cfg)
    msg = str(info.value)
    assert "franka_panda" in msg and "grasp_to_tool" in msg and "\n" not in msg
    if outcome == "refused":
        assert "does not name its gripper" in msg and "candidates.gripper" in msg
    else:
        assert "'barrett_bh8'" in msg
    # the config settles it
    poses, _ = imported_report(
        config({"path": str(path), "frame": "object", "gripper": "franka_panda"}), report
    )
    assert_pose(poses[0], expected_tool())
    assert report["grasp_frame"]["chosen_by"] == "config"


def test_run_output_and_summary_name_the_gripper(tmp_path, capsys):
    pytest.importorskip("h5py")
    cfg = tmp_path / "mug.yaml"
    cfg.write_text(
        yaml.safe_dump(
            {
                **mug_config(format="acronym", limit=40).to_dict(),
                "output": {"dir": str(tmp_path / "run")},
            }
        )
    )
    assert main(["run", str(cfg), "--out", str(tmp_path / "run")]) == 0
    out = capsys.readouterr().out
    assert "  gripper       franka_panda (named by the file)\n" in out
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["grasp_frame"]["gripper"] == "franka_panda"
    assert summary["grasp_frame"]["chosen_by"] == "file"


# ------------------------------------------------------- a file in the wrong format


def _files_of_every_kind(tmp_path: Path) -> dict[str, Path]:
    h5py = pytest.importorskip("h5py")
    files = {}
    files["hdf5"] = _acronym_file(tmp_path / "a.h5", "panda")
    files["npy"] = tmp_path / "a.npy"
    np.save(files["npy"], np.tile(np.eye(4), (2, 1, 1)))
    files["zip"] = tmp_path / "a.npz"
    np.savez(files["zip"], transforms=np.tile(np.eye(4), (2, 1, 1)))
    files["pickle"] = tmp_path / "a.pkl"
    files["pickle"].write_bytes(pickle.dumps({"grasps": [1, 2]}, protocol=4))
    files["json"] = tmp_path / "a.json"
    files["json"].write_text(json.dumps({"grasps": {"transforms": []}}))
    files["yaml"] = tmp_path / "a.yaml"
    files["yaml"].write_text("# GraspGen\ngrasps:\n  transforms: []\n")
    files["csv"] = tmp_path / "a.csv"
    files["csv"].write_text("x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n")
    del h5py
    return files


#: (kind of file, format it is read as, what the message must say)
WRONG = [
    ("hdf5", "graspgen", "this is an HDF5 file; use format: acronym"),
    ("hdf5", "csv", "this is an HDF5 file; use format: acronym"),
    ("npy", "acronym", "this is a NumPy .npy array; use format: npy or graspnet"),
    ("zip", "graspgen", "zip archive .*; use format: npz, contact_graspnet or graspnet"),
    ("zip", "npy", "zip archive .*; use format: npz, contact_graspnet or graspnet"),
    ("pickle", "npz", "this is a Python pickle; no grasp format reads it"),
    ("json", "csv", "this is JSON text; use format: graspgen"),
    ("json", "acronym", "this is JSON text; use format: graspgen"),
    ("yaml", "contact_graspnet", "this is YAML text; use format: graspgen"),
    ("csv", "graspgen", r"this is a CSV table \(header x,y,z,qw,qx,qy,qz\); use format: csv"),
    ("csv", "graspnet", r"this is a CSV table .*; use format: csv"),
]


@pytest.mark.parametrize(
    ("kind", "fmt", "message"), WRONG, ids=[f"{k}-as-{f}" for k, f, _ in WRONG]
)
def test_a_file_in_the_wrong_format_is_named(tmp_path, kind, fmt, message):
    path = _files_of_every_kind(tmp_path)[kind]
    cam = {"camera_pose": {"xyz": [0, 0, 1]}} if fmt == "contact_graspnet" else {}
    with pytest.raises(InputError, match=message) as info:
        generate_candidates(config({"path": str(path), "format": fmt, **cam}))
    assert str(info.value).startswith(f"{path}: format {fmt} reads ")
    assert "\n" not in str(info.value)


def test_every_kind_is_read_by_the_format_it_names(tmp_path):
    """The sniffer never refuses a file its own suggestion reads (no false alarms)."""
    from gcm_pipeline.sources.files.sniff import EXPECTED_KINDS, check_format, sniff

    for kind, path in _files_of_every_kind(tmp_path).items():
        found = sniff(path)
        assert found is not None and found.kind == kind
        for fmt in found.formats:
            assert kind in EXPECTED_KINDS[fmt]
            check_format(path, fmt)  # no error


def test_hdf5_read_as_graspgen_on_the_command_line(tmp_path, capsys):
    """The issue's case: it said "'utf-8' codec can't decode byte 0x89"."""
    pytest.importorskip("h5py")
    cfg = tmp_path / "c.yaml"
    doc = mug_config(format="acronym").to_dict()
    doc["candidates"]["format"] = "graspgen"
    cfg.write_text(yaml.safe_dump(doc))
    code = main(["run", str(cfg), "--out", str(tmp_path / "run")])
    line = assert_one_line_error(code, capsys.readouterr().err)
    assert "this is an HDF5 file; use format: acronym" in line and "utf-8" not in line
    assert not (tmp_path / "run").exists()


# ------------------------------------------------------------ hostile grasp files


@pytest.mark.parametrize("fmt", ["csv", "npy", "graspgen", "isaac_grasp"])
def test_a_grasp_absurdly_far_away_is_refused_naming_it(tmp_path, fmt):
    """It was reported as "points are degenerate ... try another manifold.projection"."""
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 2, 3] = [0.1, 0.2, 0.3]
    poses[1, 0, 3] = 1e25
    extra: dict = {}
    if fmt == "csv":
        path = tmp_path / "g.csv"
        rows = [f"{float(p[0, 3])!r},0,{float(p[2, 3])!r},1,0,0,0" for p in poses]
        path.write_text("x,y,z,qw,qx,qy,qz\n" + "\n".join(rows) + "\n")
        where = f"{path}:3: position (1e+25, 0, 0.2)"
    elif fmt == "npy":
        path = tmp_path / "g.npy"
        np.save(path, poses)
        where = f"{path}: grasp 1 (0-based): position (1e+25, 0, 0.2)"
    elif fmt == "graspgen":
        path = tmp_path / "g.json"
        path.write_text(json.dumps({"grasps": {"transforms": poses.tolist()}}))
        extra = {"gripper": "franka_panda"}
        where = f"{path}: grasp 1 (0-based): position (1e+25, 0, 0.2)"
    else:
        path = tmp_path / "g.yaml"
        grasps = {
            f"g{i}": {"position": p[:3, 3].tolist(), "orientation": {"w": 1, "xyz": [0, 0, 0]}}
            for i, p in enumerate(poses)
        }
        path.write_text(yaml.safe_dump({"format": "isaac_grasp", "grasps": grasps}))
        extra = {"gripper": "franka_panda"}
        where = f"{path}: grasp 'g1': position (1e+25, 0, 0.2)"
    fmt = "graspgen" if fmt == "isaac_grasp" else fmt
    with pytest.raises(InputError) as info:
        generate_candidates(config({"path": str(path), "format": fmt, **extra}))
    msg = str(info.value)
    assert msg.startswith(where), msg
    assert (info.value.row, info.value.value) == (1, 1e25)
    assert "farther than 1000 m" in msg and "\n" not in msg
    poses[1, 0, 3] = 999.0  # within the bound: read
    if fmt == "npy":
        np.save(path, poses)
        generate_candidates(config({"path": str(path), "format": fmt}))


def test_a_long_csv_cell_is_refused_and_short_text_costs_its_size(tmp_path):
    """20,000 grasps with one 100,000-character cell asked for 59.6 GiB (fixed-width text)."""
    import tracemalloc

    path = tmp_path / "g.csv"
    rows = ["x,y,z,qw,qx,qy,qz,label"] + ["0.1,0,0.2,1,0,0,0,a"] * 20_000
    rows[501] = "0.1,0,0.2,1,0,0,0," + "b" * 100_000
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(InputError) as info:
        generate_candidates(config({"path": str(path)}))
    assert str(info.value) == (
        f"{path}:502: column 'label': a cell of 100,000 characters; a CSV cell holds at "
        "most 256 (gcm_pipeline.bounds.MAX_CSV_CELL)"
    )
    # one text cell of 250 characters: the old 2-D text array took 20,000 x 8 x 250 x 4 bytes
    rows[501] = "0.1,0,0.2,1,0,0,0," + "b" * 250
    path.write_text("\n".join(rows) + "\n")
    from gcm_pipeline.sources.files import read_grasp_file

    tracemalloc.start()
    try:
        _, columns = read_grasp_file(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert columns["label"][500] == "b" * 250 and columns["label"][0] == "a"
    assert peak < 60e6, peak  # the label column alone is 20,000 x 250 x 4 = 20 MB


def test_an_hdf5_text_declaring_a_huge_size_is_refused_before_it_is_read(tmp_path):
    """An 8 KiB file whose object/file declares 1.5 GB cost 1.5 GiB before it was refused."""
    h5py = pytest.importorskip("h5py")
    if not Path("/proc/self/status").is_file():
        pytest.skip("needs Linux's /proc/self/status (VmHWM)")
    path = tmp_path / "huge.h5"
    with h5py.File(path, "w") as f:
        f["grasps/transforms"] = np.tile(np.eye(4), (3, 1, 1))
        f["grasps/qualities/flex/object_in_gripper"] = np.ones(3)
        f.create_dataset("object/file", shape=(), dtype="S1500000000")  # never written
    assert path.stat().st_size < 16_384
    code = (
        "import resource, sys\n"
        "from gcm_pipeline.errors import InputError\n"
        "from gcm_pipeline.sources.files import read_grasp_file\n"
        "try:\n"
        f"    read_grasp_file({str(path)!r})\n"
        "except InputError as exc:\n"
        "    print(exc)\n"
        "kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss\n"  # the HDF5 reader
        # this process's own peak: VmHWM of its memory map. Not RUSAGE_SELF: Linux keeps
        # the high-water mark of the process that exec'd it (pytest, 1.4 GB late in a run)
        "hwm = [ln for ln in open('/proc/self/status') if ln.startswith('VmHWM:')]\n"
        "print(max(kids, int(hwm[0].split()[1])))\n"
    )
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    message, kib = done.stdout.strip().splitlines()
    assert message == (
        f"{path}: object/file declares 1,500,000,000 bytes (shape (), dtype |S1500000000); "
        "a text takes at most 4,096: the file is corrupt"
    )
    # KiB: far below the 1.5 GB declared (reading it cost 2.49 GB); about 130 MB here,
    # the interpreter and its libraries
    assert int(kib) < 400_000


def test_a_file_without_a_known_suffix_gets_a_suggestion(tmp_path):
    path = _files_of_every_kind(tmp_path)["hdf5"].rename(tmp_path / "grasps.dat")
    with pytest.raises(
        InputError,
        match=r"suffix '\.dat'; .*\(it looks like an HDF5 file: "
        r"format: acronym\)$",
    ):
        generate_candidates(config({"path": str(path)}))


@pytest.mark.parametrize(
    ("cell", "key", "what"),
    [("abc", "y", "not a number"), ("inf", "y", "non-finite value inf")],
)
def test_a_bad_csv_grasp_cell_carries_file_line_and_column(tmp_path, cell, key, what):
    path = tmp_path / "g.csv"
    path.write_text(f"x,y,z,qw,qx,qy,qz\n0.1,0,0.2,1,0,0,0\n\n0.1,{cell},0.2,1,0,0,0\n")
    with pytest.raises(InputError) as info:
        read_grasp_file(path)
    assert str(info.value).startswith(f"{path}:4: column 'y': {what}")
    assert (info.value.path, info.value.row, info.value.key) == (path, 4, key)


def test_a_csv_grasp_row_of_the_wrong_width_and_a_bad_quaternion_carry_the_line(tmp_path):
    path = tmp_path / "g.csv"
    path.write_text("x,y,z,qw,qx,qy,qz\n0.1,0,0.2,1,0,0,0\n0.1,0,0.2,1,0,0\n")
    with pytest.raises(InputError) as info:
        read_grasp_file(path)
    assert (info.value.path, info.value.row, info.value.value) == (path, 3, 6)
    path.write_text("x,y,z,qw,qx,qy,qz\n0.1,0,0.2,1,0,0,0\n0.1,0,0.2,2,0,0,0\n")
    with pytest.raises(InputError, match="has norm 2, expected 1") as info:
        read_grasp_file(path)
    assert (info.value.path, info.value.row, info.value.value) == (path, 3, 2.0)


def test_an_unknown_gripper_carries_the_value_and_the_choices():
    from gcm_pipeline.config.gripper_spec import load_gripper

    with pytest.raises(ConfigError) as info:
        load_gripper("franka_pandaa")
    assert (info.value.value, "franka_panda" in info.value.choices) == ("franka_pandaa", True)
    assert info.value.choices == tuple(sorted(info.value.choices))


def test_an_unknown_grasp_file_format_carries_the_value_and_the_choices(tmp_path):
    path = tmp_path / "g.txt"
    path.write_text("x")
    with pytest.raises(InputError, match="cannot tell the grasp file format") as info:
        read_grasp_file(path)
    err = info.value
    assert (err.path, err.key, err.value) == (path, "candidates.format", ".txt")
    assert err.choices == ("acronym", "csv", "npy", "npz")
    with pytest.raises(InputError, match="unknown grasp file format 'xyz'") as info:
        read_grasp_file(path, format="xyz")
    assert (info.value.value, info.value.choices) == ("xyz", ("acronym", "csv", "npy", "npz"))
