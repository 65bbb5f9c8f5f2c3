"""The scene's layers: one path per grasp class, gripper glyphs, level of detail, the
object painted by reachability, the reach envelope, and tables too small or too large."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import meshcat
import numpy as np
import pytest
import umsgpack
from helpers import decode_commands

from gcm_pipeline.config import Config
from gcm_pipeline.config.gripper_spec import load_gripper
from gcm_pipeline.errors import PublishError
from gcm_pipeline.geometry.dualquat import dq_from_matrix, dq_from_pos_quat
from gcm_pipeline.outputs import html as pub_html
from gcm_pipeline.outputs import plots, scene_glyphs
from gcm_pipeline.outputs import scene as pub_scene
from gcm_pipeline.outputs.scene_envelope import envelope_points
from gcm_pipeline.outputs.scene_glyphs import GripperGlyph, grasp_classes, grasp_positions
from gcm_pipeline.outputs.scene_paint import reachability_paint
from gcm_pipeline.outputs.scene_shapes import SceneShape, translation
from gcm_pipeline.pipeline.outputs import gripper_glyph, scene_options
from gcm_pipeline.table import GraspTable

_REASONS = ("no_ik", "collision_self", "collision_object", "approach")
_LAYER_KEYS = {"path", "group", "label", "color", "count", "visible"}


def f32(ext: umsgpack.Ext) -> np.ndarray:
    return np.frombuffer(ext.data, dtype=np.float32)


def config(**extra) -> Config:
    return Config.from_dict(
        {
            "object": {
                "shape": "cylinder",
                "dims": {"radius": 0.035, "height": 0.22},
                "pose": {"xyz": [0.5, 0.0, 0.0]},
            },
            "candidates": {"source": "cylinder_side", "count": 12},
            "ranking": {"top_k": 5},
            **extra,
        }
    )


def table(robot, n: int = 90, seed: int = 1) -> GraspTable:
    """Reachable grasps (FK of perturbed home poses, ranked by manipulability) and
    unreachable ones far away, with four reasons in unequal numbers."""
    rng = np.random.default_rng(seed)
    n_r = n // 3
    q = np.clip(
        robot.home + rng.normal(0.0, 0.25, (n_r, robot.nq)), robot.lower + 1e-3, robot.upper - 1e-3
    )
    m = robot.fk(q)
    mu = m[rng.integers(0, n_r, n - n_r)].copy()
    mu[:, 0, 3] += 1.0
    reach = np.arange(n) < n_r
    reason = np.where(reach, "", np.array(_REASONS)[np.arange(n) % 7 % 4])
    manip = np.where(reach, rng.uniform(0.01, 0.12, n), np.nan)
    rank = np.zeros(n, dtype=np.int64)
    rank[np.argsort(-manip[:n_r])] = np.arange(1, n_r + 1)
    qs = np.full((n, robot.nq), np.nan)
    qs[:n_r] = q
    return GraspTable(
        {
            "dq": dq_from_matrix(np.concatenate([m, mu])),
            "reachable": reach,
            "reason": reason,
            "manipulability": manip,
            "rank": rank,
            "q": qs,
        }
    )


def objects(commands: list[dict]) -> dict[str, dict]:
    return {c["path"]: c["object"] for c in commands if c["type"] == "set_object"}


def n_vertices(obj: dict) -> int:
    return len(f32(obj["geometries"][0]["data"]["attributes"]["position"]["array"])) // 3


def under(grasps: GraspTable) -> dict:
    """An ``object`` section: a can under the reachable grasps, which reach down onto it."""
    pos = grasp_positions(grasps)[np.asarray(grasps["reachable"])].mean(axis=0)
    xyz = (pos - [0.0, 0.0, 0.15]).tolist()
    return {"shape": "cylinder", "dims": {"radius": 0.08, "height": 0.1}, "pose": {"xyz": xyz}}


@pytest.fixture(scope="module")
def drawn(panda):
    grasps = table(panda)
    options = scene_options(config(object=under(grasps)))
    html, info = pub_html.render_scene_html(grasps, None, panda, options)
    return grasps, decode_commands(html), info


def test_each_class_is_a_layer_with_the_tables_count(drawn):
    grasps, commands, info = drawn
    layers = {lay["path"]: lay for lay in info.layers}
    assert all(set(lay) == _LAYER_KEYS for lay in info.layers)
    json.dumps(info.to_dict())
    reach = np.asarray(grasps["reachable"])
    rank = np.asarray(grasps["rank"])
    reason = np.asarray(grasps["reason"])
    assert layers["/grasps/reachable/top"]["count"] == 5
    assert layers["/grasps/reachable/rest"]["count"] == reach.sum() - 5
    assert ((rank >= 1) & (rank <= 5)).sum() == 5
    for r in _REASONS:
        lay = layers[f"/grasps/unreachable/{r}"]
        assert lay["count"] == int((reason[~reach] == r).sum()) > 0
        assert lay["group"] == "unreachable"
        assert lay["color"] == scene_glyphs.hex_color(plots.REASON_COLORS[r])
    assert sum(lay["count"] for lay in info.layers if lay["group"] != "scene") == len(grasps)
    # every grasp is drawn once: a glyph of its class (all fit the budget)
    objs = objects(commands)
    nv = len(scene_options(config()).gripper.template())
    for path, lay in layers.items():
        if lay["group"] != "scene":
            assert n_vertices(objs[f"/meshcat{path}/glyphs"]) == lay["count"] * nv, path
            assert info.lod["classes"][path] == {
                "count": lay["count"],
                "glyphs": lay["count"],
                "points": 0,
            }
    # the scene's own layers, each drawn at its path
    assert {"/robot", "/object", "/object_reachability", "/envelope"} <= set(layers)
    assert {layers[p]["group"] for p in ("/robot", "/object", "/envelope")} == {"scene"}
    for path in layers:
        assert any(p.startswith(f"/meshcat{path}/") or p == f"/meshcat{path}" for p in objs), path
    assert layers["/object_reachability"]["label"].startswith("object painted by reachability")


def test_envelope_starts_hidden_and_lies_in_reach(drawn, panda):
    _, commands, info = drawn
    (lay,) = [lay for lay in info.layers if lay["path"] == "/envelope"]
    assert lay["visible"] is False
    assert all(lay["visible"] for lay in info.layers if lay["path"] != "/envelope")
    hide = [c for c in commands if c["type"] == "set_property" and c["path"] == "/meshcat/envelope"]
    assert [(c["property"], c["value"]) for c in hide] == [("visible", False)]
    pts = envelope_points(panda, np.eye(4))
    assert len(pts) == lay["count"]
    np.testing.assert_array_equal(pts, envelope_points(panda, np.eye(4)))  # seeded
    assert np.linalg.norm(pts - panda.shoulder, axis=1).max() <= panda.max_reach
    assert np.linalg.norm(pts - panda.shoulder, axis=1).max() > 0.8 * panda.max_reach
    base = translation((1.0, 2.0, 0.5))
    np.testing.assert_allclose(envelope_points(panda, base), pts + [1.0, 2.0, 0.5])
    obj = objects(commands)["/meshcat/envelope/points"]
    assert n_vertices(obj) == lay["count"]


@pytest.mark.parametrize("name", ["franka_panda", "robotiq_2f_85", "robotiq_2f_140"])
def test_glyph_fingers_stand_at_the_grippers_opening(name):
    gripper = load_gripper(name)
    glyph = gripper_glyph(gripper)
    seg = glyph.template().reshape(-1, 2, 3)
    # the fingers: the two segments along the approach (z) off the axis
    fingers = [s for s in seg if np.allclose(s[0, :2], s[1, :2]) and abs(s[0, 1]) > 1e-9]
    assert len(fingers) == 2
    ys = sorted(s[0, 1] for s in fingers)
    assert ys[1] - ys[0] == pytest.approx(gripper.max_width)
    tip = max(s[:, 2].max() for s in fingers)
    assert tip == pytest.approx(gripper.finger_tip)
    assert min(s[:, 2].min() for s in fingers) == pytest.approx(-gripper.finger_length)
    assert np.all(seg[:, :, 0] == 0.0)  # drawn in the plane of approach and closing
    # the stem runs back along the approach from the palm
    stem = [s for s in seg if np.allclose(s[:, :2], 0.0)]
    assert len(stem) == 1 and stem[0][:, 2].min() < -gripper.finger_length


def test_suction_cup_and_default_glyphs():
    cup = gripper_glyph(load_gripper("single_suction_cup_30mm"))
    assert cup.kind == "suction"
    pts = cup.template()
    lip = pts[np.isclose(pts[:, 2], 0.0)]
    assert np.linalg.norm(lip[:, :2], axis=1).max() == pytest.approx(0.025)
    assert pts[:, 2].min() < -0.069
    assert gripper_glyph(None) == GripperGlyph()
    with pytest.raises(PublishError, match="opening"):
        GripperGlyph(opening=0.0)
    with pytest.raises(PublishError, match="kind"):
        GripperGlyph(kind="magnet")


def test_scene_options_take_the_runs_gripper():
    assert scene_options(config()).gripper.name == "franka_panda"  # the Panda carries its hand
    cfg = config(candidates={"source": "antipodal", "gripper": "robotiq_2f_85"})
    assert scene_options(cfg).gripper.opening == pytest.approx(0.085)
    ur5 = config(robot={"spec": "ur5", "tool": "single_suction_cup_30mm"})
    assert scene_options(ur5).gripper.kind == "suction"
    bare = config(robot={"spec": "ur5"}, candidates={"source": "file", "path": "g.npy"})
    assert scene_options(bare).gripper.name == "default"  # no gripper named
    named = scene_options(bare, file_gripper="robotiq_2f_140").gripper
    assert named.name == "robotiq_2f_140"


def test_level_of_detail_caps_glyphs_and_dots(panda):
    grasps = table(panda, n=600)
    options = dataclasses.replace(scene_options(config()), glyph_budget=50, point_budget=120)
    html, info = pub_html.render_scene_html(grasps, None, None, options)
    lod = info.lod
    assert lod["glyphs"] == 50 and lod["points"] == 120
    classes = lod["classes"]
    assert classes["/grasps/reachable/top"]["glyphs"] == 5  # the top band first, whole
    counts = {lay["path"]: lay["count"] for lay in info.layers}
    for path, c in classes.items():
        assert c["count"] == counts[path]  # the table's classes, whatever is drawn
        assert c["glyphs"] + c["points"] <= c["count"]
    objs = objects(decode_commands(html))
    nv = len(options.gripper.template())
    for path, c in classes.items():
        if c["glyphs"]:
            assert n_vertices(objs[f"/meshcat{path}/glyphs"]) == c["glyphs"] * nv
        if c["points"]:
            assert objs[f"/meshcat{path}/points"]["object"]["type"] == "Points"
            assert n_vertices(objs[f"/meshcat{path}/points"]) == c["points"]
    # the reachable rest's glyphs are its best-ranked grasps
    rest = grasp_classes(grasps, 5)[1]
    ranks = np.asarray(grasps["rank"])[rest.rows]
    assert np.all(np.diff(ranks) > 0)
    with pytest.raises(PublishError, match="glyph_budget"):
        dataclasses.replace(options, glyph_budget=-1)


def _two_sided(n: int = 300, seed: int = 0) -> tuple[SceneShape, GraspTable]:
    """A box whose +x side is grasped reachably (approach -x) and -x side unreachably."""
    rng = np.random.default_rng(seed)
    box = SceneShape("box", translation((0.5, 0.1, 0.2)), size=(0.1, 0.1, 0.1))
    half = n // 2
    off = rng.uniform(-0.04, 0.04, (n, 2))
    pos = np.array([0.5, 0.1, 0.2]) + np.column_stack([np.zeros(n), off])
    # grasp frame z (approach) along -x for the first half, +x for the other
    rot_minus = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    rot_plus = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    m = np.tile(np.eye(4), (n, 1, 1))
    m[:half, :3, :3], m[half:, :3, :3] = rot_minus, rot_plus
    m[:, :3, 3] = pos
    reach = np.arange(n) < half
    grasps = GraspTable(
        {"dq": dq_from_matrix(m), "reachable": reach, "reason": np.where(reach, "", "no_ik")}
    )
    return box, grasps


def test_paint_tells_the_reachable_side_from_the_other():
    box, grasps = _two_sided()
    paint = reachability_paint(box, grasps, np.asarray(grasps["reachable"]))
    local = paint.points - np.array([0.5, 0.1, 0.2])
    plus, minus = local[:, 0] > 0.049, local[:, 0] < -0.049
    assert plus.sum() > 100 and minus.sum() > 100
    assert np.isfinite(paint.share[plus]).mean() > 0.9
    assert np.all(paint.share[plus][np.isfinite(paint.share[plus])] == 1.0)
    assert np.isfinite(paint.share[minus]).mean() > 0.9
    assert np.all(paint.share[minus][np.isfinite(paint.share[minus])] == 0.0)
    # grasps away from the object paint nothing, even when their axes point at it
    dq = np.asarray(grasps["dq"])
    far = np.tile(np.eye(4), (50, 1, 1))
    far[:, :3, :3] = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]  # approach +x
    far[:, :3, 3] = [-0.5, 0.1, 0.2]  # 1 m before the -x side
    more = GraspTable(
        {
            "dq": np.concatenate([dq, dq_from_matrix(far)]),
            "reachable": np.r_[np.asarray(grasps["reachable"]), np.ones(50, bool)],
        }
    )
    again = reachability_paint(box, more, np.asarray(more["reachable"]))
    np.testing.assert_array_equal(again.share, paint.share)
    # contact points, when the table has them, place the grasps instead
    swapped = grasps.with_columns(
        contact_x=np.where(np.asarray(grasps["reachable"]), 0.45, 0.55),
        contact_y=np.full(len(grasps), 0.1),
        contact_z=np.full(len(grasps), 0.2),
    )
    paint = reachability_paint(box, swapped, np.asarray(grasps["reachable"]))
    assert np.nanmean(paint.share[minus]) == 1.0 and np.nanmean(paint.share[plus]) == 0.0
    # the summary: a histogram of the painted shares and their mean
    summary = paint.summary()
    ok = np.isfinite(paint.share)
    assert summary["painted"] == ok.sum() and sum(summary["histogram"]) == ok.sum()
    assert summary["mean"] == pytest.approx(paint.share[ok].mean())


def test_painted_scene_and_its_summary():
    box, grasps = _two_sided()
    html, info = pub_html.render_scene_html(grasps, None, None, pub_scene.SceneOptions(object=box))
    (lay,) = [lay for lay in info.layers if lay["path"] == "/object_reachability"]
    assert lay["count"] == info.paint["points"] > 1000
    obj = objects(decode_commands(html))["/meshcat/object_reachability"]
    assert obj["object"]["type"] == "Mesh" and n_vertices(obj) == lay["count"]
    hist = info.paint["histogram"]
    assert hist[0] > 100 and hist[-1] > 100  # the two sides: 0 and 1
    assert 0.2 < info.paint["mean"] < 0.8


def test_zero_reachable_and_zero_grasps(panda):
    grasps = table(panda)
    none = grasps.with_columns(
        reachable=np.zeros(len(grasps), bool),
        reason=np.full(len(grasps), "no_ik"),
        rank=np.zeros(len(grasps), np.int64),
    )
    html, info = pub_html.render_scene_html(none, None, panda, scene_options(config()))
    layers = {lay["path"]: lay for lay in info.layers}
    assert layers["/grasps/reachable/top"]["count"] == 0
    assert layers["/grasps/reachable/rest"]["count"] == 0
    assert layers["/grasps/unreachable/no_ik"]["count"] == len(grasps)
    assert info.n_reachable == 0 and "/grasps/reachable" not in info.paths
    assert info.paint["mean"] == 0.0 or info.paint["painted"] == 0
    paths = {c["path"] for c in decode_commands(html)}
    assert not any(p.startswith("/meshcat/grasps/reachable") for p in paths)
    html, info = pub_html.render_scene_html(GraspTable(), None, panda, scene_options(config()))
    assert [lay["group"] for lay in info.layers] == ["scene"] * len(info.layers)
    assert info.glyph == "none" and info.paint is None and info.lod == {}
    assert "MeshCat.Viewer" in html


def big_table(n: int, seed: int = 0) -> GraspTable:
    """``n`` grasps around (0.5, 0, 0.1), 60 % reachable, ranked; four reasons."""
    rng = np.random.default_rng(seed)
    quat = rng.normal(size=(n, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    pos = np.array([0.5, 0.0, 0.1]) + rng.normal(0.0, 0.05, (n, 3))
    reach = rng.random(n) < 0.6
    manip = np.where(reach, rng.uniform(0.01, 0.1, n), np.nan)
    rank = np.zeros(n, dtype=np.int64)
    rows = np.flatnonzero(reach)
    rank[rows[np.argsort(-manip[rows])]] = np.arange(1, len(rows) + 1)
    return GraspTable(
        {
            "dq": dq_from_pos_quat(pos, quat, check=False),
            "reachable": reach,
            "reason": np.where(reach, "", np.array(_REASONS)[rng.integers(0, 4, n)]),
            "manipulability": manip,
            "rank": rank,
        }
    )


def big_scene(path: Path, n: int) -> pub_scene.SceneInfo:
    """Write the scene.html of ``n`` grasps and a cylinder; print its size and build time."""
    grasps = big_table(n)
    obj = SceneShape("cylinder", translation((0.5, 0.0, 0.0)), radius=0.04, height=0.2)
    start = time.perf_counter()
    info = pub_html.write_scene_html(path, grasps, None, None, pub_scene.SceneOptions(object=obj))
    print(
        f"\n{n:,} grasps: scene.html {path.stat().st_size / 1e6:.1f} MB, "
        f"built and written in {time.perf_counter() - start:.1f} s"
    )
    return info


def test_two_million_grasps_stay_a_page_of_tens_of_mb(tmp_path: Path):
    n = 2_000_000
    info = big_scene(tmp_path / "scene.html", n)
    assert (tmp_path / "scene.html").stat().st_size < 40_000_000
    assert info.lod["glyphs"] == scene_glyphs.GLYPH_BUDGET
    assert info.lod["points"] == scene_glyphs.POINT_BUDGET
    grasp_layers = [lay for lay in info.layers if lay["group"] != "scene"]
    assert sum(lay["count"] for lay in grasp_layers) == n
    assert info.n_reachable + info.n_unreachable == n


def test_palette_stays_clear_of_viridis():
    from matplotlib import colormaps

    viridis = colormaps["viridis"](np.linspace(0.0, 1.0, 256))[:, :3]
    palette = plots.reason_palette([*plots.REASON_COLORS, "x1", "x2", "x3", "x4", "x5"])
    for reason, rgb in palette.items():
        dist = np.linalg.norm(viridis - np.asarray(rgb), axis=1).min()
        assert dist > 0.2, (reason, rgb, dist)
    # and the reasons from each other
    colors = np.array(list(palette.values()))
    gaps = np.linalg.norm(colors[:, None] - colors[None], axis=2)
    assert gaps[np.triu_indices(len(colors), 1)].min() > 0.2


def test_live_scene_has_the_same_layers(panda):
    grasps = table(panda, n=30)
    window = pub_html.RecordingWindow()
    vis = meshcat.Visualizer(window=window)
    info = pub_scene.build_scene(vis, grasps, None, panda, scene_options(config()))
    _, static = pub_html.render_scene_html(grasps, None, panda, scene_options(config()))
    assert info.layers == static.layers
