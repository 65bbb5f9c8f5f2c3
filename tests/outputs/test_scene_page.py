"""Browser tests of scene.html's page: legend, toggles, picking and posing, the top-k tour.

Headless Chromium over the DevTools protocol (``tests/cdp.py``) opens the
self-contained page from disk; the tests read the DOM and meshcat's three.js
scene (``viewer.scene_tree``), click like a user, and compare what the page
shows with the grasp table and Pinocchio's forward kinematics of the Panda.
The table is ``scene_table`` (FK of perturbed home configurations, a few
unreachable grasps far away) with pre-grasps and retreats solved by IK: the
pre-grasp 10 cm behind the grasp along its approach axis, the retreat 10 cm
up, as the reach engine defines them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cdp import Page
from scipy.spatial.transform import Rotation
from test_browser import scene_table

from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.outputs import robot_view
from gcm_pipeline.outputs.html import write_scene_html
from gcm_pipeline.outputs.robot_view import ROT_X90, RobotPoser
from gcm_pipeline.outputs.scene import SceneOptions
from gcm_pipeline.table import GraspTable

APPROACH = 0.10  # [m] pre-grasp behind the grasp, retreat up
SIZE = (1000, 700)
ROOT = np.eye(4)
ROOT[:3, :3] = ROT_X90.T  # meshcat's root: the z-up world into three.js's y-up


def solve_ik(robot, q0: np.ndarray, target: np.ndarray, iters: int = 60) -> np.ndarray:
    """Damped least squares from ``q0`` to poses ``target`` (N, 4, 4); NaN rows where it fails."""
    q = q0.copy()
    for _ in range(iters):
        cur = robot.fk(q)
        err_p = target[:, :3, 3] - cur[:, :3, 3]
        rot = target[:, :3, :3] @ cur[:, :3, :3].transpose(0, 2, 1)
        err = np.concatenate([err_p, Rotation.from_matrix(rot).as_rotvec()], axis=1)
        jac = robot.jacobian(q)
        jjt = jac @ jac.transpose(0, 2, 1) + 1e-6 * np.eye(6)
        q = q + np.einsum("nji,nj->ni", jac, np.linalg.solve(jjt, err[..., None])[..., 0])
    cur = robot.fk(q)
    ok = np.linalg.norm(cur[:, :3, 3] - target[:, :3, 3], axis=1) < 1e-7
    ok &= np.all((q >= robot.lower) & (q <= robot.upper), axis=1)
    return np.where(ok[:, None], q, np.nan)


def approach_table(robot) -> GraspTable:
    """``scene_table`` with q_pregrasp, q_retreat (IK), q_rejected and clearance."""
    grasps, _ = scene_table(robot)
    n = len(grasps)
    reach = np.asarray(grasps["reachable"])
    q = np.asarray(grasps["q"], dtype=float)
    poses = dq_to_matrix(np.asarray(grasps["dq"]))
    pre = poses.copy()
    pre[:, :3, 3] -= APPROACH * poses[:, :3, 2]
    ret = poses.copy()
    ret[:, 2, 3] += APPROACH
    q_pre = np.full_like(q, np.nan)
    q_ret = np.full_like(q, np.nan)
    q_pre[reach] = solve_ik(robot, q[reach], pre[reach])
    q_ret[reach] = solve_ik(robot, q[reach], ret[reach])
    rejected = np.full_like(q, np.nan)
    rejected[~reach] = robot.home
    rng = np.random.default_rng(5)
    return grasps.with_columns(
        q_pregrasp=q_pre,
        q_retreat=q_ret,
        q_rejected=rejected,
        clearance=np.where(reach, rng.uniform(0.005, 0.05, n), np.nan),
    )


@pytest.fixture(scope="module")
def page_file(tmp_path_factory, panda):
    grasps = approach_table(panda)
    out = tmp_path_factory.mktemp("scene_page") / "scene.html"
    options = SceneOptions(top_k=5, blend_limit=1.0)
    info = write_scene_html(out, grasps, None, panda, options)
    return grasps, info, out


def open_page(tmp_path: Path, html: Path) -> Page:
    page = Page(tmp_path / "profile", size=SIZE)
    page.open(html)
    page.wait_for("window.gcm && gcm.state.ready", 40)
    return page


def visual_matrices(page: Page) -> dict[str, np.ndarray]:
    """World matrices (4, 4) of the robot's visual objects as three.js holds them."""
    data = page.eval(
        """(() => {
        viewer.scene.updateMatrixWorld(true);
        const out = {};
        for (const v of gcm.data.kinematics.visuals) {
            const o = viewer.scene_tree.find(["meshcat"].concat(v.path.split("/"))).object;
            out[v.path] = Array.from(o.matrixWorld.elements);
        }
        return out;
    })()"""
    )
    return {k: np.array(v).reshape(4, 4).T for k, v in data.items()}


def test_legend_shows_the_tables_counts(tmp_path, page_file):
    grasps, _, html = page_file
    reach = np.asarray(grasps["reachable"])
    reasons, counts = np.unique(np.asarray(grasps["reason"])[~reach], return_counts=True)
    with open_page(tmp_path, html) as page:
        rows = page.eval(
            """[...document.querySelectorAll('#gcm-legend .gcm-class')].map(e =>
                [e.dataset.group, e.dataset.class, Number(e.dataset.count),
                 e.querySelector('.gcm-count').textContent])"""
        )
        assert page.errors == []
    shown = {(g, c): n for g, c, n, _ in rows}
    assert all(str(n) == text for _, _, n, text in rows)
    assert sum(n for (g, _), n in shown.items() if g == "reachable") == int(reach.sum()) == 120
    unreach = {c: n for (g, c), n in shown.items() if g == "unreachable"}
    assert unreach == dict(zip(reasons.tolist(), counts.tolist(), strict=True))


def test_a_toggle_hides_exactly_one_layer(tmp_path, page_file):
    _, info, html = page_file
    js_visible = """(() => Object.fromEntries(gcm.data.layers.map(l => [l.path,
        viewer.scene_tree.find(["meshcat"].concat(l.path.split("/").filter(s => s)))
            .object.visible])))()"""
    with open_page(tmp_path, html) as page:
        before = page.eval(js_visible)
        assert set(before) >= {"/grasps/reachable", "/grasps/unreachable", "/robot"}
        assert all(before.values())
        target = "/grasps/unreachable"
        box = page.eval(
            f"""(() => {{ const r = document.querySelector('input[data-path="{target}"]')
                .getBoundingClientRect(); return [r.x + r.width / 2, r.y + r.height / 2]; }})()"""
        )
        page.click(*box)
        after = page.eval(js_visible)
        assert after[target] is False
        assert {k: v for k, v in after.items() if k != target} == {
            k: v for k, v in before.items() if k != target
        }
        checked = f"document.querySelector('input[data-path=\"{target}\"]').checked"
        assert page.eval(checked) is False
        # a hidden layer's grasps are not picked
        k = page.eval("gcm.data.grasps.reachable.indexOf(false)")
        xy = page.eval(f"gcm.project({k})")
        page.click(*xy)
        assert page.eval("gcm.state.lastPick") != k
        assert page.errors == []


def _pickable_grasp(page: Page, reachable: bool = True) -> tuple[int, list[float]]:
    """The first (best-ranked) grasp of that kind inside the view with no other grasp within
    3 px (an unreachable one: no reachable grasp within 14 px, which a click would prefer)."""
    found = page.eval(
        f"""(() => {{
        const want = {str(reachable).lower()};
        const rect = viewer.renderer.domElement.getBoundingClientRect();
        const g = gcm.data.grasps, n = g.row.length;
        const xy = gcm.projectAll();
        for (let k = 0; k < n; k++) {{
            if (g.reachable[k] !== want || !xy[k]) continue;
            const [x, y] = xy[k];
            if (x < rect.left + 20 || x > rect.right - 20) continue;
            if (y < rect.top + 40 || y > rect.bottom - 20) continue;
            let clear = true;
            for (let j = 0; j < n; j++) {{
                if (j === k || !xy[j]) continue;
                const d = Math.hypot(xy[j][0] - x, xy[j][1] - y);
                if (d < 3 || (!want && g.reachable[j] && d < 14)) clear = false;
            }}
            if (clear) return [k, xy[k]];
        }}
        return null;
    }})()"""
    )
    assert found is not None
    return found[0], found[1]


def test_a_click_on_a_grasp_poses_the_arm_at_it(tmp_path, page_file, panda):
    grasps, _, html = page_file
    poser = RobotPoser(panda)
    with open_page(tmp_path, html) as page:
        k, (x, y) = _pickable_grasp(page)
        row = page.eval(f"gcm.data.grasps.row[{k}]")
        page.click(x + 2.0, y - 1.0)  # a user's click lands near the glyph's centre
        assert page.eval("gcm.state.selected") == k
        page.wait_for("!gcm.state.playing", 20)
        shown = visual_matrices(page)
        details = page.eval("document.getElementById('gcm-details').textContent")
        page.screenshot(tmp_path / "posed.png")
        assert page.errors == []
    q = np.asarray(grasps["q"], dtype=float)[row]
    expected = {path: ROOT @ t for path, t in poser.placements(q)}  # base: identity
    assert set(shown) == set(expected) and len(shown) >= 8
    for path, t in expected.items():
        np.testing.assert_allclose(shown[path], t, atol=1e-5, err_msg=path)
    # FK of the shown configuration is the grasp: the grasp frame's pose, read off the
    # shown hand (fixed to the grasp frame's joint) through Pinocchio's hand -> TCP offset
    tool_joint = panda.model.frames[panda.grasp_frame_id].parentJoint
    name = next(o.name for o in poser.visual.geometryObjects if o.parentJoint == tool_joint)
    path = f"robot/visuals/{name}"
    hand = dict(poser.placements(q))[path]
    offset = np.linalg.solve(hand, panda.fk(q)[0])
    tcp = np.linalg.solve(ROOT, shown[path]) @ offset
    grasp = dq_to_matrix(np.asarray(grasps["dq"])[row : row + 1])[0]
    np.testing.assert_allclose(tcp, grasp, atol=1e-6)
    assert f"row{row}" in details and "rank" in details and "q_pregrasp -> q" in details


def test_picking_a_top_k_entry_and_an_unreachable_grasp(tmp_path, page_file, panda):
    grasps, _, html = page_file
    with open_page(tmp_path, html) as page:
        entries = page.eval(
            "[...document.querySelectorAll('#gcm-topk-list li')].map(e => Number(e.dataset.row))"
        )
        rank = np.asarray(grasps["rank"])
        assert entries == [int(np.flatnonzero(rank == r)[0]) for r in range(1, 6)]
        third = page.eval(
            """(() => { const r = document.querySelectorAll('#gcm-topk-list li')[2]
                .getBoundingClientRect(); return [r.x + 20, r.y + r.height / 2]; })()"""
        )
        page.click(*third)
        assert page.eval("gcm.data.grasps.row[gcm.state.selected]") == entries[2]
        page.wait_for("!gcm.state.playing", 20)
        q = np.asarray(grasps["q"])[entries[2]]
        np.testing.assert_allclose(page.eval("gcm.state.posed"), q, atol=1e-12)
        # an unreachable grasp: its reason, and the rejected solution marked as such
        k, (x, y) = _pickable_grasp(page, reachable=False)
        page.click(x, y)
        assert page.eval("gcm.state.selected") == k
        details = page.eval("document.getElementById('gcm-details').textContent")
        assert "reasonno_ik" in details and "rejected solution" in details
        assert page.eval("gcm.state.rejected") is True
        np.testing.assert_allclose(page.eval("gcm.state.posed"), panda.home, atol=1e-12)
        assert page.errors == []


def test_the_tour_never_leaves_the_approach_paths(tmp_path, page_file, panda):
    """Every frame of the meshcat animation, sampled between keys too, stays near its grasp."""
    grasps, info, html = page_file
    poser = RobotPoser(panda)
    tool_joint = panda.model.frames[panda.grasp_frame_id].parentJoint
    name = next(o.name for o in poser.visual.geometryObjects if o.parentJoint == tool_joint)
    path = f"robot/visuals/{name}"
    q0 = np.asarray(grasps["q"])[0]
    offset = np.linalg.solve(dict(poser.placements(q0, scaled=False))[path], panda.fk(q0)[0])
    with open_page(tmp_path, html) as page:
        tour = page.eval("gcm.data.tour")
        samples = page.eval(
            f"""(() => {{
            viewer.animator.pause();
            const o = viewer.scene_tree.find(["meshcat"].concat("{path}".split("/"))).object;
            const out = [];
            for (const seg of gcm.data.tour) {{
                const n = 40, a = seg.start_s + 1e-4, b = seg.end_s - 1e-4;
                for (let i = 0; i <= n; i++) {{
                    const t = a + (b - a) * i / n;
                    viewer.animator.seek(t);
                    viewer.scene.updateMatrixWorld(true);
                    out.push([seg.row, t, Array.from(o.matrixWorld.elements)]);
                }}
            }}
            return out;
        }})()"""
        )
        assert page.errors == []
    assert len(tour) == 5 and info.top_k == 5
    assert info.animation_cuts == 5  # 4 between the grasps, 1 back to the first
    assert info.animation_s == pytest.approx(tour[-1]["end_s"])
    assert all(seg["approach"] and seg["retreat"] for seg in tour)
    poses = dq_to_matrix(np.asarray(grasps["dq"]))
    far = []
    for row, _, m in samples:
        tcp = np.linalg.solve(ROOT, np.array(m).reshape(4, 4).T) @ offset
        far.append(np.linalg.norm(tcp[:3, 3] - poses[row][:3, 3]))
    far = np.array(far)
    assert far.max() <= APPROACH + 0.005, far.max()
    assert far.max() >= APPROACH - 0.005  # the pre-grasps and retreats are shown
    # and the rank-1 grasp itself is shown (its hold)
    assert far.min() < 1e-5


def test_tour_keys_cut_between_grasps():
    a = np.array([0.0, 0.5, 0.0, -2.0, 0.0, 1.5, 0.8])
    qs = np.stack([a, a + 0.1, a + np.r_[2.0, np.zeros(6)]])
    pre = qs - 0.05
    ret = qs + 0.05
    pre[1] = np.nan  # no approach configured for that grasp: held, then cut
    ret[2] = qs[2] + np.r_[0.0, 2.0, np.zeros(5)]  # another branch: a cut, not a blend
    tour = robot_view.tour_keys(qs, pre, ret, blend_limit=0.5)
    frames = [f for f, _ in tour.keys]
    assert frames == sorted(frames)
    # every key lies on one grasp's approach or retreat line (or is a stored configuration)
    for frame, q in tour.keys:
        seg = next(s for s in tour.segments if s.start <= frame <= s.end)
        on = []
        for end in (pre[seg.index], ret[seg.index]):
            if np.all(np.isfinite(end)):
                d = end - qs[seg.index]
                s = np.clip((q - qs[seg.index]) @ d / (d @ d), 0.0, 1.0)
                on.append(np.abs(qs[seg.index] + s * d - q).max())
        assert min(on, default=np.abs(q - qs[seg.index]).max()) < 1e-12 or any(
            np.array_equal(q, c) for c in (*qs, *pre, *ret)
        ), (frame, q)
    # two keys on one frame: a cut; 2 between the grasps, 1 back to the first (the far
    # retreat is not shown)
    dup = [f for f, n in zip(*np.unique(frames, return_counts=True), strict=True) if n > 1]
    assert len(dup) == 3 and tour.cuts == 3
    assert [s.approach for s in tour.segments] == [True, False, True]
    assert [s.retreat for s in tour.segments] == [True, True, False]
    assert np.array_equal(tour.keys[-1][1], qs[0])
    # nothing to animate: one grasp held, no approach, no retreat
    assert not robot_view.tour_keys(qs[:1]).moves


def test_no_reachable_grasp_and_no_configurations(tmp_path, panda):
    grasps, _ = scene_table(panda)
    n = len(grasps)
    none = grasps.with_columns(
        reachable=np.zeros(n, bool),
        reason=np.full(n, "no_ik"),
        rank=np.zeros(n, np.int64),
        q=np.full((n, panda.nq), np.nan),
    )
    no_q = GraspTable({k: grasps[k] for k in grasps.columns if k != "q"})
    for label, table in (("none", none), ("no_q", no_q)):
        out = tmp_path / label
        out.mkdir()
        info = write_scene_html(out / "scene.html", table, None, panda, SceneOptions(top_k=5))
        with open_page(out, out / "scene.html") as page:
            empty = page.eval("(document.getElementById('gcm-empty') || {}).textContent")
            entries = page.eval("document.querySelectorAll('#gcm-topk-list li').length")
            k = page.eval("gcm.data.grasps.row.length - 1")
            page.eval(f"gcm.select({k})")
            page.eval("gcm.select(0)")
            details = page.eval("document.getElementById('gcm-details').textContent")
            assert page.errors == [], label
        if label == "none":
            assert empty == "no reachable grasp" and entries == 0
            assert info.animation_s == 0.0 and info.animation_cuts == 0
        else:
            assert empty is None and entries == 5  # ranked, listed, but not posed
            assert "no configuration in the table" in details


def _odd_joints(extra=None):
    """A Pinocchio model with the joint kinds Pinocchio's URDF reader makes besides RX/RY/RZ:
    unaligned revolute and prismatic axes, a continuous (cos, sin) joint, a tool on a fixed
    placement; box visuals, one scaled."""
    import coal
    import pinocchio as pin

    model = pin.Model()
    geom = pin.GeometryModel()
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    joints = [
        pin.JointModelRUBZ(),
        pin.JointModelRevoluteUnaligned(*axis),
        pin.JointModelPrismaticUnaligned(*axis[::-1]),
        pin.JointModelPY(),
        pin.JointModelRX(),
        *([extra] if extra is not None else []),
    ]
    parent = 0
    rng = np.random.default_rng(2)
    for i, joint in enumerate(joints):
        place = pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(0.0, 0.2, 3))
        parent = model.addJoint(parent, joint, place, f"j{i}")
        obj = pin.GeometryObject(f"box{i}", parent, pin.SE3.Random(), coal.Box(0.05, 0.04, 0.03))
        obj.meshScale = np.array([1.0, 2.0, 0.5]) if i == 2 else np.ones(3)
        geom.addGeometryObject(obj)
    tool = model.addFrame(pin.Frame("tool", parent, 0, pin.SE3.Random(), pin.FrameType.OP_FRAME))
    robot = type("Odd", (), {})()
    robot.model, robot.visual_model, robot.grasp_frame_id = model, geom, tool
    robot.nq, robot.home = model.nq, pin.neutral(model)
    return robot


def test_the_pages_forward_kinematics_is_pinocchios(tmp_path, panda):
    """Panda, UR5 with its tool, a URDF arm of primitives with a fixed flange, and
    Pinocchio's other 1-dof joint kinds: the page's placements equal Pinocchio's."""
    import pinocchio as pin
    from urdfs import write_arm

    from gcm_pipeline.config.robot_spec import load_robot

    robots = {
        "panda": panda,
        "ur5": load_robot("ur5"),
        "arm": load_robot(write_arm(tmp_path / "arm")),
        "odd": _odd_joints(),
    }
    for label, robot in robots.items():
        out = tmp_path / label
        out.mkdir(exist_ok=True)
        write_scene_html(
            out / "scene.html", GraspTable(), None, robot, SceneOptions(envelope=False)
        )
        lim = np.full(robot.model.nq, 2.0)
        qs = [pin.randomConfiguration(robot.model, -lim, lim) for _ in range(3)]
        poser = RobotPoser(robot)
        with open_page(out, out / "scene.html") as page:
            assert page.eval("gcm.data.kinematics.unsupported") == []
            for q in qs:
                shown = page.eval(f"gcm.placements({q.tolist()})")
                tool = np.array(page.eval(f"gcm.toolPose({q.tolist()})")).reshape(4, 4)
                for (path, m), (want_path, want) in zip(shown, poser.placements(q), strict=True):
                    assert path == want_path
                    np.testing.assert_allclose(np.reshape(m, (4, 4)), want, atol=1e-12)
                pin.framesForwardKinematics(robot.model, poser.data, q)
                want_tool = poser.data.oMf[robot.grasp_frame_id].homogeneous
                np.testing.assert_allclose(tool, want_tool, atol=1e-12, err_msg=label)
            assert page.errors == [], label


def test_the_live_viewer_serves_the_page_with_its_panel(tmp_path, panda):
    from gcm_pipeline.outputs import live
    from gcm_pipeline.outputs.scene import PublishOptions

    grasps = approach_table(panda)
    options = PublishOptions(scene=SceneOptions(top_k=5, blend_limit=1.0))
    viewer = live.open_viewer(grasps, None, panda, options)
    try:
        assert viewer.panel and viewer.info.animation_cuts == 5
        with Page(tmp_path / "profile", size=SIZE) as page:
            page.open(viewer.url)
            page.wait_for("window.gcm && gcm.state.ready", 40)
            counts = page.eval(
                """[...document.querySelectorAll('#gcm-legend .gcm-class')].map(e =>
                    [e.dataset.group, Number(e.dataset.count)])"""
            )
            k, (x, y) = _pickable_grasp(page)
            page.click(x, y)
            assert page.eval("gcm.state.selected") == k
            page.wait_for("!gcm.state.playing", 20)
            shown = visual_matrices(page)
            row = page.eval(f"gcm.data.grasps.row[{k}]")
            assert page.errors == []
    finally:
        viewer.close()
    reach = np.asarray(grasps["reachable"])
    assert sum(n for g, n in counts if g == "reachable") == reach.sum()
    assert sum(n for g, n in counts if g == "unreachable") == (~reach).sum()
    q = np.asarray(grasps["q"], dtype=float)[row]
    for path, t in RobotPoser(panda).placements(q):
        np.testing.assert_allclose(shown[path], ROOT @ t, atol=1e-5, err_msg=path)


def test_layers_come_from_the_scene_or_are_derived(page_file):
    """``info.layers`` (per-reason paths, rank bands) is used as given; without it the layers
    are derived from ``info.paths`` and the legend, and each picked grasp names its layer."""
    from types import SimpleNamespace

    from gcm_pipeline.outputs.scene_page import page_data, scene_layers

    grasps, info, _ = page_file
    derived = scene_layers(info)
    paths = [layer["path"] for layer in derived]
    assert paths == list(info.paths)
    by_path = {layer["path"]: layer for layer in derived}
    assert by_path["/grasps/reachable"]["count"] == 120
    assert by_path["/grasps/unreachable"]["classes"] == [
        {"label": "no_ik", "color": info.legend["unreachable"]["no_ik"]["color"], "count": 30}
    ]
    given = [
        {"path": "/grasps/reachable/top", "group": "reachable", "label": "top 5",
         "color": None, "count": 5, "visible": True},
        {"path": "/grasps/reachable/rest", "group": "reachable", "label": "rest",
         "color": None, "count": 115, "visible": True},
        {"path": "/grasps/unreachable/no_ik", "group": "unreachable", "label": "no_ik",
         "color": "#999999", "count": 30, "visible": False},
        {"path": "/robot", "group": "scene", "label": "robot", "color": None, "count": None,
         "visible": True},
    ]  # fmt: skip
    scene = SimpleNamespace(**{**info.to_dict(), "layers": given})
    assert scene_layers(scene) == given
    data = page_data(grasps, None, SceneOptions(top_k=5), scene)
    layer = data["grasps"]["layer"]
    reach = data["grasps"]["reachable"]
    assert layer[:5] == [0] * 5 and set(layer[5:120]) == {1} and reach[:120] == [True] * 120
    assert set(layer[120:]) == {2} and data["top_k"] == 5 and data["kinematics"] is None


def test_joint_types_the_page_cannot_move_are_posed_from_placements(tmp_path):
    """A spherical joint: the best grasps are posed from Pinocchio's placements, no motion."""
    import pinocchio as pin

    from gcm_pipeline.geometry.dualquat import dq_from_matrix

    robot = _odd_joints(pin.JointModelSpherical())
    poser = RobotPoser(robot)
    lim = np.full(robot.model.nq, 2.0)
    q = np.array([pin.randomConfiguration(robot.model, -lim, lim) for _ in range(3)])
    tcp = []
    for qi in q:
        pin.framesForwardKinematics(robot.model, poser.data, qi)
        tcp.append(poser.data.oMf[robot.grasp_frame_id].homogeneous)
    grasps = GraspTable(
        {
            "dq": dq_from_matrix(np.array(tcp)),
            "reachable": np.ones(3, bool),
            "reason": np.full(3, ""),
            "q": q,
            "manipulability": np.array([0.1, 0.2, 0.3]),
            "rank": np.array([2, 1, 3]),
        }
    )
    html = tmp_path / "scene.html"
    write_scene_html(html, grasps, None, robot, SceneOptions(top_k=3, envelope=False))
    with open_page(tmp_path, html) as page:
        assert page.eval("gcm.data.kinematics.unsupported") == ["JointModelSpherical"]
        hint = page.eval("document.getElementById('gcm-hint').textContent")
        assert "JointModelSpherical" in hint and "precomputed" in hint
        for k in (0, 2):
            assert page.eval(f"gcm.select({k})") is True
            row = page.eval(f"gcm.data.grasps.row[{k}]")
            shown = visual_matrices(page)
            for path, t in poser.placements(q[row]):
                np.testing.assert_allclose(shown[path], ROOT @ t, atol=1e-5, err_msg=path)
        assert page.eval("gcm.state.playing") is False
        assert "without motion" in page.eval("document.getElementById('gcm-details').textContent")
        assert page.errors == []
