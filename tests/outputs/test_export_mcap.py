"""gcm export --format mcap: a ROS 2 bag read back with rosbags and with Foxglove's mcap library.

The run behind these tests is configs/box.yaml made quick, with a retreat (straight up) and
an obstacle, written by ``gcm run``. The bag is compared with the run's own files:
grasps.csv (rank order, poses, the metric) and configurations.npz (the joint solutions).
The moveit_msgs definitions the package writes are compared with the real ones
(tests/data/moveit_msgs, copied from moveit/moveit_msgs).
"""

from __future__ import annotations

import csv
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import CONFIGS, DATA, QUICK, assert_one_line_error
from scipy.spatial.transform import Rotation

from gcm_pipeline.cli import main
from gcm_pipeline.outputs.export_mcap import MOVEIT_MSGS, TOPICS, ros_message, typestore
from gcm_pipeline.ranking.metrics import METRIC_COLUMNS

OBSTACLE = "[{shape: box, dims: {size: [0.1, 0.1, 0.3]}, pose: {xyz: [0.3, 0.35, 0.15]}}]"
SETTINGS = (
    "densify.subdivisions=2",
    "retreat={direction: [0, 0, 1], distance: 0.05, steps: 5}",
    f"environment.obstacles={OBSTACLE}",
)
JOINTS = [f"panda_joint{i}" for i in range(1, 8)]


def gcm_run(out: Path, *more: str) -> Path:
    sets = [a for s in (*SETTINGS, *more) for a in ("--set", s)]
    code = main(["run", str(CONFIGS / "box.yaml"), "--out", str(out), *QUICK, *sets])
    assert code == 0
    return out


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    return gcm_run(tmp_path_factory.mktemp("mcap") / "run")


@pytest.fixture(scope="module")
def bag(run, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bag") / "grasps.mcap"
    assert main(["export", str(run), "--format", "mcap", "--out", str(out)]) == 0
    return out


def ranked_rows(run: Path) -> tuple[list[str], list[list[str]], np.ndarray]:
    """grasps.csv's header, its ranked rows best first, and their row indices."""
    with (run / "grasps.csv").open(newline="") as fh:
        header, *rows = list(csv.reader(fh))
    rank = [int(r[header.index("rank")] or 0) for r in rows]
    order = sorted((k, i) for i, k in enumerate(rank) if k > 0)
    return header, [rows[i] for _, i in order], np.array([i for _, i in order])


def read_bag(bag: Path) -> list[tuple[str, str, int, object]]:
    """(topic, type, log time, message) of every message, with rosbags' reader."""
    from rosbags.rosbag2 import Reader

    store = typestore()
    with Reader(bag) as reader:
        return [
            (c.topic, c.msgtype, t, store.deserialize_cdr(raw, c.msgtype))
            for c, t, raw in reader.messages()
        ]


def stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def test_the_bag_has_a_grasp_and_a_trajectory_per_reachable_grasp_in_rank_order(run, bag):
    from rosbags.rosbag2 import Reader

    header, ranked, rows = ranked_rows(run)
    with Reader(bag) as reader:
        topics = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
    assert topics == {
        "/tf_static": ("tf2_msgs/msg/TFMessage", 1),
        "/scene_markers": ("visualization_msgs/msg/MarkerArray", 1),
        "/grasps": ("moveit_msgs/msg/Grasp", len(ranked)),
        "/grasp_trajectories": ("trajectory_msgs/msg/JointTrajectory", len(ranked)),
    }
    reachable = [
        r[header.index("reachable")] == "true" for r in csv.reader((run / "grasps.csv").open())
    ]
    assert len(ranked) == sum(reachable) > 10
    msgs = read_bag(bag)
    grasps = [m for topic, _, _, m in msgs if topic == "/grasps"]
    trajectories = [m for topic, _, _, m in msgs if topic == "/grasp_trajectories"]
    assert [g.id for g in grasps] == [f"rank_{k}" for k in range(1, len(ranked) + 1)]
    metric = yaml.safe_load((run / "config.yaml").read_text())["ranking"]["metric"]
    metric = METRIC_COLUMNS[metric]  # yoshikawa: the manipulability column
    for g, row in zip(grasps, ranked, strict=True):
        p, o = g.grasp_pose.pose.position, g.grasp_pose.pose.orientation
        want = [float(row[header.index(c)]) for c in ("x", "y", "z")]
        np.testing.assert_allclose([p.x, p.y, p.z], want, atol=1e-9)  # the world frame
        q = [float(row[header.index(c)]) for c in ("qx", "qy", "qz", "qw")]
        got = Rotation.from_quat([o.x, o.y, o.z, o.w]).as_matrix()
        np.testing.assert_allclose(got, Rotation.from_quat(q).as_matrix(), atol=1e-9)
        assert g.grasp_pose.header.frame_id == "world"
        assert g.grasp_quality == pytest.approx(float(row[header.index(metric)]), rel=1e-12)
        assert g.pre_grasp_approach.direction.header.frame_id == "panda_hand_tcp"
        assert g.pre_grasp_approach.desired_distance == pytest.approx(0.08)
        retreat = g.post_grasp_retreat
        assert retreat.direction.header.frame_id == "panda_link0"
        assert retreat.desired_distance == pytest.approx(0.05)
        v = retreat.direction.vector
        np.testing.assert_allclose([v.x, v.y, v.z], [0, 0, 1], atol=1e-12)  # base not rotated
        assert list(g.pre_grasp_posture.joint_names) == [
            "panda_finger_joint1",
            "panda_finger_joint2",
        ]
    # the first grasp is the run's rank-1 grasp (the one gcm show prints first)
    assert grasps[0].id == "rank_1" and ranked[0][header.index("rank")] == "1"
    with np.load(run / "configurations.npz") as data:
        conf = {k: data[k][rows] for k in ("q_pregrasp", "q", "q_retreat")}
    for i, t in enumerate(trajectories):
        assert list(t.joint_names) == JOINTS and t.header.frame_id == "panda_link0"
        assert len(t.points) == 3
        for point, name in zip(t.points, ("q_pregrasp", "q", "q_retreat"), strict=True):
            np.testing.assert_array_equal(point.positions, conf[name][i])
        times = [p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in t.points]
        assert times == [0.0, 1.0, 2.0]


def test_log_times_increase_and_every_header_carries_its_log_time(bag):
    msgs = read_bag(bag)
    times = [t for _, _, t, _ in msgs]
    assert times == sorted(times) and len(set(times)) == len(times)
    assert [topic for topic, *_ in msgs[:2]] == ["/tf_static", "/scene_markers"]
    for topic, _, t, m in msgs:
        if topic == "/grasps":
            assert stamp_ns(m.grasp_pose.header) == t
        elif topic == "/grasp_trajectories":
            assert stamp_ns(m.header) == t
        elif topic == "/scene_markers":
            assert {stamp_ns(mk.header) for mk in m.markers} == {t}
            assert {mk.header.frame_id for mk in m.markers} == {"world"}
        else:
            assert stamp_ns(m.transforms[0].header) == t
    assert times[0] > 1.7e18  # the run's creation time, not 1970


def test_static_transform_and_markers_show_the_run_scene(run, bag):
    header, ranked, _ = ranked_rows(run)
    msgs = {topic: m for topic, _, _, m in read_bag(bag) if topic != "/grasps"}
    (tf,) = msgs["/tf_static"].transforms
    assert (tf.header.frame_id, tf.child_frame_id) == ("world", "panda_link0")
    assert (tf.transform.translation.x, tf.transform.rotation.w) == (0.0, 1.0)
    markers = msgs["/scene_markers"].markers
    by_ns: dict[str, list] = {}
    for mk in markers:
        by_ns.setdefault(mk.ns, []).append(mk)
    assert set(by_ns) == {"object", "table", "obstacles", "grasps_reachable", "grasps_unreachable"}
    (box,) = by_ns["object"]
    assert box.type == 1  # CUBE
    assert (box.scale.x, box.scale.y, box.scale.z) == pytest.approx((0.06, 0.06, 0.15))
    p = box.pose.position
    assert (p.x, p.y, p.z) == pytest.approx((0.45, -0.15, 0.075))
    yaw = Rotation.from_quat(
        [
            box.pose.orientation.x,
            box.pose.orientation.y,
            box.pose.orientation.z,
            box.pose.orientation.w,
        ]
    ).as_euler("xyz")
    assert yaw == pytest.approx([0, 0, np.radians(30)])
    (table,) = by_ns["table"]
    assert table.pose.position.z + table.scale.z / 2 == pytest.approx(0.0)  # top at height 0
    (obstacle,) = by_ns["obstacles"]
    assert obstacle.pose.position.y == pytest.approx(0.35)
    with (run / "grasps.csv").open(newline="") as fh:
        rows = list(csv.reader(fh))[1:]
    reachable = [r[header.index("reachable")] == "true" for r in rows]
    good, bad = by_ns["grasps_reachable"], by_ns["grasps_unreachable"]
    assert len(good) == sum(reachable) and len(bad) == len(rows) - sum(reachable) > 0
    assert sorted(mk.id for mk in good) == list(range(1, len(good) + 1))  # id = rank
    assert {(mk.color.g > mk.color.r) for mk in good} == {True}  # green
    assert {(mk.color.r > mk.color.g) for mk in bad} == {True}  # red
    for mk in good:
        assert mk.type == 0 and len(mk.points) == 2  # ARROW from tail to tip
        row = ranked[mk.id - 1]
        tip = [mk.points[1].x, mk.points[1].y, mk.points[1].z]
        np.testing.assert_allclose(tip, [float(row[header.index(c)]) for c in "xyz"], atol=1e-9)


def test_foxglove_mcap_library_decodes_the_bag(run, bag):
    """Foxglove's own reader and ROS 2 decoder (mcap, mcap-ros2-support) read every message
    from the schemas embedded in the file, independently of rosbags."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    _, ranked, _ = ranked_rows(run)
    with bag.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert reader.get_header().profile == "ros2"
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        assert [m.name for m in reader.iter_metadata()] == ["rosbag2"]
        decoded = [(ch.topic, msg) for _, ch, _, msg in reader.iter_decoded_messages()]
    grasps = [m for topic, m in decoded if topic == "/grasps"]
    assert len(decoded) == 2 + 2 * len(ranked)
    assert [g.id for g in grasps] == [f"rank_{k}" for k in range(1, len(ranked) + 1)]
    assert grasps[0].grasp_pose.header.frame_id == "world"


def _fields(types: dict) -> dict:
    """Each message's (field name, field type) list as rosbags parses it."""
    return {name: list(fields) for name, (_consts, fields) in types.items()}


def test_the_package_moveit_definitions_are_moveit_msgs_own(bag):
    """MOVEIT_MSGS parses to exactly the fields of moveit_msgs' .msg files, and the bag's
    embedded schemas carry them."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import get_types_from_msg

    real, ours = {}, {}
    for f in sorted((DATA / "moveit_msgs" / "msg").glob("*.msg")):
        name = f"moveit_msgs/msg/{f.stem}"
        real.update(get_types_from_msg(f.read_text(), name))
        ours.update(get_types_from_msg(MOVEIT_MSGS[name], name))
    assert (
        set(real)
        == set(MOVEIT_MSGS)
        == {
            "moveit_msgs/msg/Grasp",
            "moveit_msgs/msg/GripperTranslation",
        }
    )
    assert _fields(ours) == _fields(real)
    with Reader(bag) as reader:
        (conn,) = [c for c in reader.connections if c.topic == "/grasps"]
    schema = conn.msgdef.data
    main_part, *deps = schema.split("=" * 80 + "\nMSG: ")
    assert _fields(get_types_from_msg(main_part, "moveit_msgs/msg/Grasp")) == {
        "moveit_msgs/msg/Grasp": _fields(real)["moveit_msgs/msg/Grasp"]
    }
    dep = next(d for d in deps if d.startswith("moveit_msgs/GripperTranslation"))
    text = dep.split("\n", 1)[1]
    assert _fields(get_types_from_msg(text, "moveit_msgs/msg/GripperTranslation")) == {
        "moveit_msgs/msg/GripperTranslation": _fields(real)["moveit_msgs/msg/GripperTranslation"]
    }


def test_moveit_yaml_carries_the_arm_trajectory_with_trajectory(run, tmp_path, capsys):
    out = tmp_path / "m.yaml"
    assert main(["export", str(run), "--format", "moveit", "--trajectory", "--out", str(out)]) == 0
    grasps = yaml.safe_load(out.read_text())
    _, ranked, rows = ranked_rows(run)
    assert len(grasps) == len(ranked)
    with np.load(run / "configurations.npz") as data:
        conf = {k: data[k][rows] for k in ("q_pregrasp", "q", "q_retreat")}
    store = typestore()
    for i, g in enumerate(grasps):
        traj = g.pop("trajectory")
        assert list(g)[0] == "id" and "trajectory" not in g
        msg = ros_message(store, "trajectory_msgs/msg/JointTrajectory", traj)  # its exact fields
        assert list(msg.joint_names) == JOINTS and msg.header.frame_id == "panda_link0"
        for point, name in zip(traj["points"], ("q_pregrasp", "q", "q_retreat"), strict=True):
            assert point["positions"] == conf[name][i].tolist()
        assert [p["time_from_start"]["sec"] for p in traj["points"]] == [0, 1, 2]
        ros_message(store, "moveit_msgs/msg/Grasp", g)  # the rest is a Grasp, as before
    plain = tmp_path / "plain.yaml"
    assert main(["export", str(run), "--format", "moveit", "--out", str(plain)]) == 0
    assert all("trajectory" not in g for g in yaml.safe_load(plain.read_text()))
    code = main(
        ["export", str(run), "--format", "npz", "--trajectory", "--out", str(tmp_path / "x")]
    )
    assert_one_line_error(code, capsys.readouterr().err, "--trajectory is for --format moveit")


def test_without_a_retreat_the_trajectory_returns_to_the_pregrasp(tmp_path):
    run = gcm_run(tmp_path / "run", "retreat=null", "environment.obstacles=[]")
    out = tmp_path / "g.mcap"
    assert main(["export", str(run), "--format", "mcap", "--out", str(out)]) == 0
    trajectories = [m for topic, _, _, m in read_bag(out) if topic == "/grasp_trajectories"]
    assert trajectories
    for t in trajectories:
        assert len(t.points) == 3
        np.testing.assert_array_equal(t.points[2].positions, t.points[0].positions)
    grasps = [m for topic, _, _, m in read_bag(out) if topic == "/grasps"]
    back = grasps[0].post_grasp_retreat  # the approach reversed
    assert back.direction.header.frame_id == "panda_hand_tcp" and back.direction.vector.z == -1.0


# ------------------------------------------------------------------ bad input


def test_a_run_without_reachable_grasps_gives_a_valid_empty_bag_and_one_line(tmp_path, capsys):
    far = gcm_run(tmp_path / "far", "object.pose.xyz=[3.0, 0.0, 0.075]")
    capsys.readouterr()
    out = tmp_path / "none.mcap"
    code = main(["export", str(far), "--format", "mcap", "--out", str(out)])
    assert_one_line_error(code, capsys.readouterr().err, "no reachable grasp to export")
    msgs = read_bag(out)
    assert [topic for topic, *_ in msgs] == ["/tf_static", "/scene_markers"]
    markers = msgs[1][3].markers
    assert {mk.ns for mk in markers} >= {"object", "grasps_unreachable"}
    assert "grasps_reachable" not in {mk.ns for mk in markers}


def test_a_run_without_configurations_npz_is_one_line_and_writes_nothing(run, tmp_path, capsys):
    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    (copy / "configurations.npz").unlink()
    out = tmp_path / "g.mcap"
    for fmt, extra in (("mcap", []), ("moveit", ["--trajectory"])):
        code = main(["export", str(copy), "--format", fmt, *extra, "--out", str(out)])
        assert_one_line_error(code, capsys.readouterr().err, "no configurations.npz")
        assert not out.exists()
    np.savez(copy / "configurations.npz", q=np.zeros((3, 7)))  # not this run's
    code = main(["export", str(copy), "--format", "mcap", "--out", str(out)])
    assert_one_line_error(code, capsys.readouterr().err, "array 'q_pregrasp' is missing")
    assert not out.exists() and not list(tmp_path.glob(".*"))


def test_out_in_a_missing_folder_or_over_an_existing_file(run, bag, tmp_path, capsys):
    missing = tmp_path / "no" / "such"
    code = main(["export", str(run), "--format", "mcap", "--out", str(missing / "g.mcap")])
    line = assert_one_line_error(code, capsys.readouterr().err)
    assert line == f"error: cannot write {missing / 'g.mcap'}: {missing} does not exist"
    old = tmp_path / bag.name
    old.write_bytes(b"an earlier export")
    assert main(["export", str(run), "--format", "mcap", "--out", str(old)]) == 0
    # replaced atomically, as every export is; the same bag, byte for byte
    assert old.read_bytes() == bag.read_bytes()
    assert not list(tmp_path.glob(".*"))  # no temporary bag left beside it


def test_without_rosbags_the_mcap_export_names_the_extra(run, tmp_path, capsys, monkeypatch):
    for name in [m for m in sys.modules if m == "rosbags" or m.startswith("rosbags.")]:
        monkeypatch.setitem(sys.modules, name, None)  # import rosbags raises ImportError
    monkeypatch.setitem(sys.modules, "rosbags", None)
    out = tmp_path / "g.mcap"
    code = main(["export", str(run), "--format", "mcap", "--out", str(out)])
    assert_one_line_error(code, capsys.readouterr().err, 'pip install "gcm-pipeline[ros]"')
    assert not out.exists()


def test_the_topics_table_is_what_the_bag_holds(bag):
    assert [topic for topic, *_ in read_bag(bag)][:2] == list(TOPICS)[:2]
    assert {(topic, kind) for topic, kind, *_ in read_bag(bag)} == set(TOPICS.items())


# ------------------------------------------------------------------ markers


def test_each_scene_shape_becomes_its_marker_and_serialises():
    from gcm_pipeline.outputs import export_mcap
    from gcm_pipeline.outputs.scene_shapes import SceneShape, SceneTable
    from gcm_pipeline.table import GraspTable

    at = np.eye(4)
    at[:3, 3] = [0.5, 0.1, 0.0]
    mug = CONFIGS / "data" / "mug.obj"
    shapes = [
        SceneShape("cylinder", at, radius=0.03, height=0.2),
        SceneShape("sphere", at, radius=0.04),
        SceneShape("plane", at, size=(0.3, 0.2)),
        SceneShape("mesh", at, mesh=mug, scale=0.5),
    ]
    empty = GraspTable({"dq": np.zeros((0, 8)), "reachable": np.zeros(0, bool)})
    array = export_mcap.scene_markers(empty, shapes[0], SceneTable(height=0.7), shapes[1:], 5)
    store = typestore()
    msg = ros_message(store, "visualization_msgs/msg/MarkerArray", array)
    store.serialize_cdr(msg, "visualization_msgs/msg/MarkerArray")  # a valid message
    cylinder, table, sphere, plane, mesh = msg.markers
    assert [m.type for m in msg.markers] == [3, 1, 2, 1, 10]
    assert [m.ns for m in msg.markers] == ["object", "table", "obstacles", "obstacles", "obstacles"]
    assert [m.id for m in msg.markers[2:]] == [0, 1, 2]
    # a marker cylinder is centred; the scene's stands on its base
    c = cylinder.pose.position
    assert (c.x, c.y, c.z) == pytest.approx((0.5, 0.1, 0.1))
    assert (cylinder.scale.x, cylinder.scale.y, cylinder.scale.z) == pytest.approx(
        (0.06, 0.06, 0.2)
    )
    assert table.pose.position.z + table.scale.z / 2 == pytest.approx(0.7)
    assert (sphere.scale.x, sphere.scale.z) == pytest.approx((0.08, 0.08))
    assert (plane.scale.x, plane.scale.y, plane.scale.z) == pytest.approx((0.3, 0.2, 0.002))
    assert mesh.mesh_resource == mug.resolve().as_uri() and mesh.scale.x == 0.5
    assert {stamp_ns(m.header) for m in msg.markers} == {5}


def test_grasp_arrows_keep_the_best_ranked_and_spread_the_rest(run, monkeypatch):
    from gcm_pipeline.outputs import export_mcap
    from gcm_pipeline.rundir.grasps_csv import read_grasps_csv

    grasps = read_grasps_csv(run / "grasps.csv")
    reachable = np.asarray(grasps["reachable"], bool)
    monkeypatch.setattr(export_mcap, "MAX_ARROWS", 5)
    arrows = export_mcap.grasp_arrows(grasps, 0)
    good = [m for m in arrows if m["ns"] == "grasps_reachable"]
    bad = [m for m in arrows if m["ns"] == "grasps_unreachable"]
    assert [m["id"] for m in good] == [1, 2, 3, 4, 5]
    rows = np.flatnonzero(~reachable)
    assert len(rows) > 5 and len(bad) == 5
    assert bad[0]["id"] == rows[0] and bad[-1]["id"] == rows[-1]
    assert all(not reachable[m["id"]] for m in bad)


def test_top_keeps_the_best_grasps_and_their_trajectories(run, tmp_path):
    from gcm_pipeline import export_run

    out = tmp_path / "top.mcap"
    assert export_run(run, "mcap", top=3, out=out).rows == 3
    msgs = read_bag(out)
    grasps = [m for topic, _, _, m in msgs if topic == "/grasps"]
    trajectories = [m for topic, _, _, m in msgs if topic == "/grasp_trajectories"]
    assert [g.id for g in grasps] == ["rank_1", "rank_2", "rank_3"]
    _, _, rows = ranked_rows(run)
    with np.load(run / "configurations.npz") as data:
        q = data["q"][rows[:3]]
    np.testing.assert_array_equal([t.points[1].positions for t in trajectories], q)
