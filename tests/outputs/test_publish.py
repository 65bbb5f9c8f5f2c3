"""Publish stage: scene content, glyph batching, colours, camera, plots, live viewer."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import socket
import time
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import meshcat
import numpy as np
import pytest
import umsgpack
from helpers import ROOT, decode_commands

from gcm_pipeline.config import Config
from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.errors import PublishError
from gcm_pipeline.geometry.dualquat import dq_from_matrix
from gcm_pipeline.outputs import html as pub_html
from gcm_pipeline.outputs import live, plots, robot_view, scene_glyphs
from gcm_pipeline.outputs import scene as pub_scene
from gcm_pipeline.outputs.plots import PLOT_FILES, chart_points, write_plots
from gcm_pipeline.outputs.scene_shapes import SceneShape, SceneTable, translation
from gcm_pipeline.pipeline.outputs import publish_options, scene_options
from gcm_pipeline.table import GraspTable


def f32(ext: umsgpack.Ext) -> np.ndarray:
    return np.frombuffer(ext.data, dtype=np.float32)


@pytest.fixture(scope="module")
def robot(panda):
    """The shared Panda (conftest.py) under this module's name."""
    return panda


def make_config(**publish) -> Config:
    return Config.from_dict(
        {
            "object": {
                "shape": "cylinder",
                "dims": {"radius": 0.035, "height": 0.22},
                "pose": {"xyz": [0.5, 0.0, 0.0]},
            },
            "candidates": {"source": "cylinder_side", "count": 12},
            "ranking": {"top_k": 3},
            "publish": publish,
        }
    )


def make_scene(robot, n: int = 60, seed: int = 0):
    """A grasp table like the pipeline's: FK of perturbed home poses (reachable, with q)
    and far-away poses (unreachable, reasons no_ik / self_collision), plus a manifold
    over the first 6 rows."""
    rng = np.random.default_rng(seed)
    n_r = n * 2 // 3
    n_u = n - n_r
    q = robot.home + rng.normal(0.0, 0.25, (n_r, robot.nq))
    q = np.clip(q, robot.lower + 1e-3, robot.upper - 1e-3)
    m_r = robot.fk(q)
    m_u = m_r[rng.integers(0, n_r, n_u)].copy()
    m_u[:, 0, 3] += 1.5
    dq = dq_from_matrix(np.concatenate([m_r, m_u]))
    reach = np.r_[np.ones(n_r, bool), np.zeros(n_u, bool)]
    reason = np.where(reach, "", np.where(np.arange(n) % 2 == 0, "no_ik", "collision_self"))
    manip = np.r_[rng.uniform(0.01, 0.12, n_r), np.full(n_u, np.nan)]
    rank = np.zeros(n, dtype=np.int64)
    order = np.argsort(-manip[:n_r])
    rank[order] = np.arange(1, n_r + 1)
    qs = np.full((n, robot.nq), np.nan)
    qs[:n_r] = q
    nc = 6
    origin = np.where(np.arange(n) < nc, "candidate", "interpolated")
    tris = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4], [3, 5, 4]])
    chart = rng.uniform(-0.1, 0.1, (nc, 2))
    tri_of_row = np.where(np.arange(n) < nc, -1, np.arange(n) % len(tris))
    vertices = np.where(tri_of_row[:, None] >= 0, tris[tri_of_row], -1)
    weights = rng.dirichlet(np.ones(3), n)
    weights[:nc] = np.nan
    grasps = GraspTable(
        {
            "dq": dq,
            "origin": origin,
            "triangle": tri_of_row,
            "vertices": vertices,
            "weights": weights,
            "reachable": reach,
            "reason": reason,
            "q": qs,
            "manipulability": manip,
            "rank": rank,
        }
    )
    manifold = SimpleNamespace(
        chart=chart,
        triangles=tris,
        dropped=np.zeros((0, 3), dtype=np.int64),
        dropped_reason=np.array([], dtype=str),
        projection="pca",
    )
    return grasps, manifold


def by_path(commands: list[dict]) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for c in commands:
        out.setdefault(c["path"], []).append(c)
    return out


@pytest.fixture(scope="module")
def scene(robot):
    grasps, manifold = make_scene(robot)
    html, info = pub_html.render_scene_html(grasps, manifold, robot, scene_options(make_config()))
    return grasps, manifold, html, info


def test_scene_paths(scene):
    _, _, html, info = scene
    paths = {c["path"] for c in decode_commands(html)}
    # a point cloud and contact points have their own scene (test_scene_cloud.py); no
    # grasp is near the object to paint it (test_scene_layers.py)
    drawn = set(pub_scene.SCENE_PATHS) - {"/cloud", "/contacts", "/object_reachability"}
    for sub in drawn:
        assert any(p == "/meshcat" + sub or p.startswith("/meshcat" + sub + "/") for p in paths), (
            sub
        )
    assert set(info.paths) == drawn
    assert any(p.startswith("/meshcat/robot/visuals/panda_link7") for p in paths)
    assert info.n_reachable == 40 and info.n_unreachable == 20
    # the page is self-contained: meshcat's viewer script is inlined, nothing is fetched
    assert "MeshCat.Viewer" in html and "<script src" not in html


def test_animation_steps_through_top_k(scene):
    _, _, html, info = scene
    anims = [c for c in decode_commands(html) if c["type"] == "set_animation"]
    assert len(anims) == 1
    clips = anims[0]["animations"]
    assert {c["path"] for c in clips} >= {"/meshcat/robot/visuals/panda_hand_0"}
    assert info.top_k == 3 and info.animation_s > 1.0


def test_scene_tour_cuts_between_grasps(robot):
    """The tour never blends from one grasp to the next, whatever the blend limit."""
    grasps, manifold = make_scene(robot)
    rank = np.asarray(grasps["rank"])
    q = np.array(grasps["q"])
    top = [int(np.flatnonzero(rank == r)[0]) for r in (1, 2, 3)]
    base = np.clip(robot.home, robot.lower, robot.upper)
    q[top[0]] = base
    q[top[1]] = base + 0.05
    q[top[2]] = base + np.r_[1.5, np.zeros(robot.nq - 1)]  # another branch
    grasps = grasps.with_columns(q=q)
    html, info = pub_html.render_scene_html(grasps, manifold, robot, scene_options(make_config()))
    assert info.top_k == 3 and info.animation_cuts == 3  # 1 -> 2, 2 -> 3, 3 -> 1
    (anim,) = [c for c in decode_commands(html) if c["type"] == "set_animation"]
    clip = next(c["clip"] for c in anim["animations"] if c["path"].endswith("panda_link1_0"))
    times = [k["time"] for k in clip["tracks"][0]["keys"]]
    # 3 held grasps (2 keys each) and the cut back to the first: nothing in between
    assert len(times) == 3 * 2 + 1 and len(set(times)) == 4
    cfg = make_config()
    cfg = Config.from_dict({**cfg.to_dict(), "continuity": {"threshold": 3.0}})
    _, info = pub_html.render_scene_html(grasps, manifold, robot, scene_options(cfg))
    assert info.animation_cuts == 3


def _object_of(commands: list[dict], path: str) -> dict:
    (cmd,) = [c for c in commands if c["type"] == "set_object" and c["path"] == path]
    return cmd["object"]


def test_glyphs_are_batched(robot):
    counts = {}
    for n in (30, 3000):
        grasps, manifold = make_scene(robot, n)
        window = pub_html.RecordingWindow()
        vis = meshcat.Visualizer(window=window)
        options = scene_options(make_config())
        info = pub_scene.build_scene(vis, grasps, manifold, robot, options)
        counts[n] = window.n_objects
        assert info.meshcat_objects == window.n_objects
        commands = [umsgpack.unpackb(b) for b in window.commands()]
        size = 0
        for band in ("top", "rest"):
            obj = _object_of(commands, f"/meshcat/grasps/reachable/{band}/glyphs")
            assert obj["object"]["type"] == "LineSegments"
            size += f32(obj["geometries"][0]["data"]["attributes"]["position"]["array"]).size
        assert size == info.n_reachable * len(options.gripper.template()) * 3
    assert counts[30] == counts[3000]


def test_colors(scene):
    grasps, _, html, info = scene
    commands = decode_commands(html)
    nv = len(scene_options(make_config()).gripper.template())
    manip = np.asarray(grasps["manipulability"])
    reachable = np.asarray(grasps["reachable"])
    lo, hi = manip[reachable].min(), manip[reachable].max()
    from matplotlib import colormaps

    viridis = colormaps["viridis"]
    classes = {c.path: c for c in scene_glyphs.grasp_classes(grasps, 3)}
    spread = []
    for band in ("top", "rest"):
        obj = _object_of(commands, f"/meshcat/grasps/reachable/{band}/glyphs")
        rgb = f32(obj["geometries"][0]["data"]["attributes"]["color"]["array"]).reshape(-1, 3)
        assert obj["materials"][0]["vertexColors"] == 2
        rows = classes[f"/grasps/reachable/{band}"].rows
        expected = viridis((manip[rows] - lo) / (hi - lo))[:, :3]
        np.testing.assert_allclose(rgb[::nv], expected, atol=1e-6)
        spread.append(rgb)
    assert np.ptp(np.concatenate(spread), axis=0).max() > 0.5  # a range of colours, not one
    for reason in ("no_ik", "collision_self"):
        obj = _object_of(commands, f"/meshcat/grasps/unreachable/{reason}/glyphs")
        urgb = f32(obj["geometries"][0]["data"]["attributes"]["color"]["array"]).reshape(-1, 3)
        assert np.allclose(urgb, plots.REASON_COLORS[reason], atol=1e-6)
    leg = info.legend
    json.dumps(info.to_dict())  # JSON-ready for the run summary
    assert leg == scene_glyphs.legend(grasps)
    assert leg["colormap"] == "viridis"
    assert leg["metric_range"] == pytest.approx([lo, hi])
    assert set(leg["unreachable"]) == {"no_ik", "collision_self"}
    assert leg["unreachable"]["no_ik"]["count"] == 10
    assert leg["unreachable"]["no_ik"]["path"] == "/grasps/unreachable/no_ik"


def test_camera_frames_scene(scene):
    grasps, _, html, info = scene
    commands = by_path(decode_commands(html))
    (prop,) = commands["/Cameras/default/rotated/<object>"]
    assert prop["property"] == "position"
    local = np.array(prop["value"])
    world = robot_view.ROT_X90 @ local
    np.testing.assert_allclose(world, info.camera["position"], atol=1e-9)
    assert not np.allclose(local, [3.0, 1.0, 0.0])  # not meshcat's default
    target = np.array(info.camera["target"])
    dist = np.linalg.norm(world - target)
    assert 0.5 < dist < 4.0
    # the target lies between the robot base and the grasps
    assert 0.0 < target[0] < 1.0 and 0.0 < target[2] < 1.0
    assert "viewer.controls.target.set(" in html


def test_objects_and_table(tmp_path: Path):
    for shape, dims in (
        ("box", {"size": [0.1, 0.2, 0.3]}),
        ("sphere", {"radius": 0.05}),
        ("plane", {"size": [0.4, 0.3]}),
    ):
        cfg = Config.from_dict(
            {
                "object": {"shape": shape, "dims": dims},
                "candidates": {"source": shape},
                "environment": {"table": {"height": -0.1}},
            }
        )
        html, info = pub_html.render_scene_html(GraspTable(), None, None, scene_options(cfg))
        commands = by_path(decode_commands(html))
        assert "/meshcat/object/shape" in commands
        table = [c for c in commands["/meshcat/environment/table"] if c["type"] == "set_transform"]
        assert np.reshape(table[0]["matrix"], (4, 4)).T[2, 3] == pytest.approx(-0.1 - 0.025)
        assert info.paths == ("/object", "/environment")
    obj = tmp_path / "tri.obj"
    obj.write_text("v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n")
    cfg = Config.from_dict(
        {
            "object": {"shape": "mesh", "mesh": str(obj), "scale": 2.0},
            "candidates": {"source": "file", "path": "g.npy"},
        }
    )
    html, info = pub_html.render_scene_html(GraspTable(), None, None, scene_options(cfg))
    commands = by_path(decode_commands(html))
    (shape,) = [c for c in commands["/meshcat/object/shape"] if c["type"] == "set_object"]
    assert shape["object"]["geometries"][0]["format"] == "obj"
    (scale,) = [c for c in commands["/meshcat/object/shape"] if c["type"] == "set_transform"]
    assert np.reshape(scale["matrix"], (4, 4))[0, 0] == pytest.approx(2.0)
    cfg = Config.from_dict(
        {"candidates": {"source": "file", "path": "g.npy"}, "environment": {"table": None}}
    )
    _, info = pub_html.render_scene_html(GraspTable(), None, None, scene_options(cfg))
    assert info.paths == ()


def test_publish_writes_what_config_asks(robot, tmp_path: Path):
    grasps, manifold = make_scene(robot)
    paths = pub_html.publish(
        grasps, manifold, robot, publish_options(make_config(html=True, plots=True)), tmp_path
    )
    assert [p.name for p in paths] == ["scene.html", *PLOT_FILES]
    assert all(p.is_file() and p.stat().st_size > 1000 for p in paths)
    only_plots = tmp_path / "plots"
    only_plots.mkdir()
    paths = pub_html.publish(
        grasps, manifold, robot, publish_options(make_config(html=False)), only_plots
    )
    assert [p.name for p in paths] == list(PLOT_FILES)
    neither = make_config(html=False, plots=False)
    assert pub_html.publish(grasps, manifold, robot, publish_options(neither), tmp_path) == []


def test_plots(robot, tmp_path: Path):
    grasps, manifold = make_scene(robot)
    counts = pub_scene.stage_counts(grasps, manifold)
    assert counts == {
        "candidates": 6,
        "triangles": 4,
        "triangles_dropped": 0,
        "densified": 60,
        "reachable": 40,
    }
    paths = write_plots(grasps, manifold, counts, tmp_path)
    assert [p.name for p in paths] == list(PLOT_FILES)
    for p in paths:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # no manifold, no reachable grasp: still three (mostly empty) plots
    empty = GraspTable({"dq": np.asarray(grasps["dq"])[:3]})
    assert len(write_plots(empty, None, {"densified": 3}, tmp_path)) == 3
    with pytest.raises(PublishError, match="does not exist"):
        write_plots(grasps, manifold, counts, tmp_path / "missing")


def test_chart_points_are_barycentric(robot):
    grasps, manifold = make_scene(robot)
    pts = chart_points(grasps, manifold)
    np.testing.assert_allclose(pts[:6], manifold.chart)
    row = 10
    v = np.asarray(grasps["vertices"])[row]
    w = np.asarray(grasps["weights"])[row]
    np.testing.assert_allclose(pts[row], w @ manifold.chart[v])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_server_fails_fast(robot):
    url = f"tcp://127.0.0.1:{_free_port()}"
    grasps, manifold = make_scene(robot, 12)
    cfg = make_config(meshcat=True, zmq_url=url, connect_timeout_s=0.5)
    start = time.monotonic()
    with pytest.raises(PublishError, match=re.escape(url)):
        live.open_viewer(grasps, manifold, robot, publish_options(cfg))
    assert time.monotonic() - start < 5.0
    with pytest.raises(PublishError, match="invalid meshcat zmq_url"):
        live.probe_server("not a url", 0.5)


def test_live_viewer(robot):
    grasps, manifold = make_scene(robot, 30)
    viewer = live.open_viewer(grasps, manifold, robot, publish_options(make_config(meshcat=True)))
    try:
        assert viewer.owns_server
        assert viewer.url.startswith("http://127.0.0.1:")
        assert viewer.zmq_url.startswith("tcp://127.0.0.1:")
        with urllib.request.urlopen(viewer.url, timeout=10) as resp:
            assert resp.status == 200
        assert live.probe_server(viewer.zmq_url, 5.0) == viewer.url
        # the server holds the scene: its static page carries our objects
        html = viewer.visualizer.window.get_scene()
        paths = {c["path"] for c in decode_commands(html)}
        assert "/meshcat/grasps/reachable/top/glyphs" in paths and "/meshcat/object/shape" in paths
        not_drawn = {"/cloud", "/contacts", "/object_reachability"}
        assert set(viewer.info.paths) == set(pub_scene.SCENE_PATHS) - not_drawn
        # a second client connects to the running server through zmq_url
        other = live.open_viewer(
            grasps,
            manifold,
            None,
            publish_options(make_config(meshcat=True, zmq_url=viewer.zmq_url)),
        )
        assert other.url == viewer.url and not other.owns_server
        other.close()
        proc = viewer._proc
    finally:
        viewer.close()
    assert proc is not None and proc.poll() is not None
    viewer.close()  # idempotent
    with pytest.raises(PublishError):
        live.probe_server(viewer.zmq_url, 0.3)


def _robot_mesh_points(commands: list[dict]) -> dict[str, np.ndarray]:
    """World vertices of every robot visual in a recorded scene (node transforms applied)."""
    transforms = {
        c["path"]: np.asarray(c["matrix"], dtype=float).reshape(4, 4).T
        for c in commands
        if c["type"] == "set_transform"
    }
    base = transforms.get("/meshcat/robot", np.eye(4))
    out: dict[str, list[np.ndarray]] = {}
    for c in commands:
        path = c["path"]
        if c["type"] != "set_object" or not path.startswith("/meshcat/robot/visuals/"):
            continue
        link = path.split("/")[4]
        geom = c["object"]["geometries"][0]
        if geom["type"] != "BufferGeometry":
            continue
        v = f32(geom["data"]["attributes"]["position"]["array"]).reshape(-1, 3)
        local = transforms.get(path, np.eye(4))
        m = base @ transforms[f"/meshcat/robot/visuals/{link}"] @ local
        out.setdefault(link, []).append(v @ m[:3, :3].T + m[:3, 3])
    return {k: np.concatenate(v) for k, v in out.items()}


@pytest.mark.parametrize("name", ["panda", "ur5"])
def test_robot_meshes_are_whole_and_embedded_once(name):
    """Every link's mesh touches the next one along the chain (the UR5's wrist and
    flange used to float apart), and each mesh is embedded once, simplified."""
    from scipy.spatial import cKDTree

    robot = load_robot(name)
    q = robot.home.copy()
    grasps = GraspTable(
        {
            "dq": dq_from_matrix(robot.fk(q)),
            "reachable": np.array([True]),
            "reason": np.array([""]),
            "q": q[None],
            "manipulability": np.array([0.05]),
            "rank": np.array([1]),
        }
    )
    cfg = Config.from_dict(
        {"robot": {"spec": name}, "candidates": {"source": "file", "path": "x.npy"}}
    )
    html, _ = pub_html.render_scene_html(grasps, None, robot, scene_options(cfg))
    commands = decode_commands(html)
    links = _robot_mesh_points(commands)
    visual = robot.build_geometry("visual")
    import coal

    meshes = [o for o in visual.geometryObjects if isinstance(o.geometry, coal.BVHModelBase)]
    names = [o.name for o in meshes]  # primitives (the UR5's tool boxes) are drawn as such
    assert sorted(links) == sorted(names)
    # one set_object per colour group of a mesh, never repeated (the animation moves nodes)
    objs = [c["path"] for c in commands if c["type"] == "set_object" and "/robot/" in c["path"]]
    assert len(objs) == len(set(objs))
    by_joint: dict[int, list[str]] = {}
    for o in meshes:
        by_joint.setdefault(int(o.parentJoint), []).append(o.name)
    joints = sorted(by_joint)
    for a, b in zip(joints[:-1], joints[1:], strict=True):
        pa = np.concatenate([links[n] for n in by_joint[a]])
        pb = np.concatenate([links[n] for n in by_joint[b]])
        gap = cKDTree(pa).query(pb)[0].min()
        assert gap < 0.01, (name, a, b, gap)
    total_faces = sum(
        len(c["object"]["geometries"][0]["data"]["index"]["array"].data) // 6
        for c in commands
        if c["type"] == "set_object"
        and "/robot/" in c["path"]
        and c["object"]["geometries"][0]["type"] == "BufferGeometry"
    )
    assert total_faces < robot_view.MESH_FACE_BUDGET * len(names) * 1.2


def test_primitive_tool_geometry_in_the_visual_model_is_drawn(monkeypatch):
    """A tool made of boxes (as a robot spec's gripper adds) is drawn with the arm."""
    import coal
    import pinocchio as pin

    robot = load_robot("ur5")
    build = robot.build_geometry

    def with_tool(kind="collision"):
        geom = build(kind)
        if kind == "visual":
            jid = robot.model.frames[robot.grasp_frame_id].parentJoint
            place = pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.05]))
            obj = pin.GeometryObject("tool_palm", jid, place, coal.Box(0.04, 0.09, 0.03))
            obj.meshColor = np.array([0.2, 0.2, 0.25, 1.0])
            geom.addGeometryObject(obj)
        return geom

    monkeypatch.setattr(robot, "build_geometry", with_tool)
    q = robot.home.copy()
    grasps = GraspTable({"dq": dq_from_matrix(robot.fk(q)), "q": q[None], "rank": np.array([1])})
    cfg = Config.from_dict(
        {"robot": {"spec": "ur5"}, "candidates": {"source": "file", "path": "x.npy"}}
    )
    commands = decode_commands(
        pub_html.render_scene_html(grasps, None, robot, scene_options(cfg))[0]
    )
    box = [c for c in commands if c["path"] == "/meshcat/robot/visuals/tool_palm/0"]
    assert box and box[0]["object"]["geometries"][0]["type"] == "BoxGeometry"
    geom = box[0]["object"]["geometries"][0]
    assert [geom["width"], geom["height"], geom["depth"]] == pytest.approx([0.04, 0.09, 0.03])
    moves = [c for c in commands if c["path"] == "/meshcat/robot/visuals/tool_palm"]
    assert moves and moves[0]["type"] == "set_transform"


def _cached_panda_mesh(robot, tmp_path, monkeypatch) -> str:
    """One of the Panda's visual meshes, with an empty mesh cache under ``tmp_path``."""
    path = next(o.meshPath for o in robot.build_geometry("visual").geometryObjects if o.meshPath)
    monkeypatch.setenv("GCM_CACHE_DIR", str(tmp_path / "cache"))
    robot_view._simplified_mesh_cached.cache_clear()
    return path


def test_simplified_robot_meshes_are_cached_on_disk(robot, tmp_path, monkeypatch):
    """The second run reads the simplified meshes from the cache instead of simplifying again."""
    path = _cached_panda_mesh(robot, tmp_path, monkeypatch)
    first = robot_view._simplified_mesh(path)
    files = list((tmp_path / "cache" / "meshes").iterdir())
    assert len(files) == 1 and files[0].suffix == ".npz"

    def no_simplify(*_args):
        raise AssertionError("simplified again although the cache holds the mesh")

    robot_view._simplified_mesh_cached.cache_clear()
    monkeypatch.setattr(robot_view, "_simplify_mesh", no_simplify)
    again = robot_view._simplified_mesh(path)
    assert [c for c, _ in again] == [c for c, _ in first]
    for (_, a), (_, b) in zip(first, again, strict=True):
        assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    robot_view._simplified_mesh_cached.cache_clear()


def test_a_damaged_or_unwritable_mesh_cache_is_rebuilt_or_skipped(robot, tmp_path, monkeypatch):
    path = _cached_panda_mesh(robot, tmp_path, monkeypatch)
    fresh = robot_view._simplified_mesh(path)
    (cached,) = (tmp_path / "cache" / "meshes").iterdir()
    cached.write_bytes(cached.read_bytes()[:100])  # truncated
    robot_view._simplified_mesh_cached.cache_clear()
    rebuilt = robot_view._simplified_mesh(path)
    assert [len(m.faces) for _, m in rebuilt] == [len(m.faces) for _, m in fresh]
    assert robot_view._read_mesh_cache(cached) is not None  # written again, whole
    # a temporary file left by a process killed while writing: removed once stale
    stale, fresh_tmp = cached.parent / ".a.npz.1.tmp", cached.parent / ".b.npz.2.tmp"
    stale.write_bytes(b"partial")
    fresh_tmp.write_bytes(b"being written")
    os.utime(stale, (time.time() - 7200, time.time() - 7200))
    cached.unlink()
    robot_view._simplified_mesh_cached.cache_clear()
    robot_view._simplified_mesh(path)
    assert not stale.exists() and fresh_tmp.exists() and cached.is_file()
    fresh_tmp.unlink()
    # files that load but are not a cache: a plain array, a scalar colour list
    with cached.open("wb") as f:
        np.save(f, np.zeros(3))
    assert robot_view._read_mesh_cache(cached) is None
    np.savez(cached.with_suffix(".x.npz"), colors=np.int64(3))
    assert robot_view._read_mesh_cache(cached.with_suffix(".x.npz")) is None
    robot_view._simplified_mesh_cached.cache_clear()
    assert [len(m.faces) for _, m in robot_view._simplified_mesh(path)] == [
        len(m.faces) for _, m in fresh
    ]
    # a cache folder that cannot be created (a file is in the way): drawn all the same
    blocker = tmp_path / "blocker"
    blocker.write_text("not a folder")
    monkeypatch.setenv("GCM_CACHE_DIR", str(blocker))
    robot_view._simplified_mesh_cached.cache_clear()
    assert [len(m.faces) for _, m in robot_view._simplified_mesh(path)] == [
        len(m.faces) for _, m in fresh
    ]
    robot_view._simplified_mesh_cached.cache_clear()


def test_the_mesh_cache_follows_an_obj_files_materials(tmp_path, monkeypatch):
    """Changing an .obj mesh's .mtl (its colours) is a new cache entry, not the old colours."""
    mesh = tmp_path / "m.obj"
    mesh.write_text(
        "mtllib m.mtl\nusemtl c\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
        "f 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
    )
    (tmp_path / "m.mtl").write_text("newmtl c\nKd 1 0 0\n")
    monkeypatch.setenv("GCM_CACHE_DIR", str(tmp_path / "cache"))
    robot_view._simplified_mesh_cached.cache_clear()
    assert [c for c, _ in robot_view._simplified_mesh(str(mesh))] == [0xFF0000]
    (tmp_path / "m.mtl").write_text("newmtl c\nKd 0 0 1\n")
    robot_view._simplified_mesh_cached.cache_clear()
    assert [c for c, _ in robot_view._simplified_mesh(str(mesh))] == [0x0000FF]
    assert len(list((tmp_path / "cache" / "meshes").iterdir())) == 2
    robot_view._simplified_mesh_cached.cache_clear()


def test_the_scene_takes_plain_options_without_a_config(tmp_path: Path):
    """A scene drawn from SceneOptions equals the one of the config they are mapped from."""
    cfg = Config.from_dict(
        {
            "object": {"shape": "sphere", "dims": {"radius": 0.04}, "pose": {"xyz": [0.4, 0, 0]}},
            "candidates": {"source": "file", "path": "g.npy"},
            "environment": {
                "table": {"height": -0.1},
                "obstacles": [
                    {"shape": "box", "dims": {"size": [0.1, 0.1, 0.1]}, "name": "crate"},
                    {"shape": "sphere", "dims": {"radius": 0.02}, "pose": {"xyz": [0, 1, 0]}},
                ],
            },
        }
    )
    options = scene_options(cfg)
    assert options.object.shape == "sphere" and options.object.radius == 0.04
    assert [o.name for o in options.obstacles] == ["crate", None]
    np.testing.assert_array_equal(options.obstacles[1].pose[:3, 3], [0.0, 1.0, 0.0])
    plain = pub_scene.SceneOptions(
        object=SceneShape("sphere", translation((0.4, 0.0, 0.0)), radius=0.04),
        table=SceneTable(height=-0.1),
        obstacles=(
            SceneShape("box", np.eye(4), size=(0.1, 0.1, 0.1), name="crate"),
            SceneShape("sphere", translation((0.0, 1.0, 0.0)), radius=0.02),
        ),
    )
    html, from_config = pub_html.render_scene_html(GraspTable(), None, None, options)
    _, from_plain = pub_html.render_scene_html(GraspTable(), None, None, plain)
    assert from_config.paths == from_plain.paths == ("/object", "/environment")
    assert from_config.camera == from_plain.camera
    paths = {c["path"] for c in decode_commands(html)}
    assert {"/meshcat/environment/crate/shape", "/meshcat/environment/obstacle_1/shape"} <= paths
    with pytest.raises(dataclasses.FrozenInstanceError):
        options.top_k = 3  # type: ignore[misc]
    assert not options.base_pose.flags.writeable


def test_meshcat_loads_only_when_a_scene_is_drawn():
    """Importing the pipeline (and so this package) does not load meshcat and its server."""
    import subprocess
    import sys

    code = (
        "import sys, gcm_pipeline.pipeline, gcm_pipeline.outputs.html, gcm_pipeline.outputs.live; "
        "print(sorted(m for m in ('meshcat', 'tornado') if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    )
    assert out.stdout.strip() == "[]"


def test_a_scene_that_cannot_be_written_whole_leaves_the_old_page(tmp_path):
    """A file-size limit (as a full disk) cuts the write: the old page stays, no temporary."""
    import subprocess
    import sys

    page = tmp_path / "panda.html"
    page.write_text("old page")
    script = (
        "import resource, signal, sys\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, 100_000))\n"
        "from gcm_pipeline.cli import main\n"
        "sys.exit(main(['robot', 'panda', '--out', sys.argv[1]]))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run(
        [sys.executable, "-c", script, str(page)], capture_output=True, text=True, env=env
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith("error: cannot write scene ") and "Traceback" not in done.stderr
    assert page.read_text() == "old page"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["panda.html"]
