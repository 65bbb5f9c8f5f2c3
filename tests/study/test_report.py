"""study.html: the study report written by a study and by ``gcm plot STUDY_DIR``.

One small real study (inline engine, the small bottle of ``test_study.py``)
is run once for the module; the browser test opens its page in headless
Chromium over the DevTools protocol, clicks a map cell and checks that the
scene shows that placement.
"""

from __future__ import annotations

import csv
import json
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from cdp import Page
from helpers import BOTTLE, ROOT, assert_one_line_error
from helpers import SMALL_STUDY as SMALL

from gcm_pipeline.cli import main
from gcm_pipeline.study import Study
from gcm_pipeline.study.report_scene import pose_matrices


def _run(folder: Path, sweep: dict) -> Path:
    path = folder / "study.yaml"
    path.write_text(yaml.safe_dump({"base": str(BOTTLE), "set": SMALL, "sweep": sweep}))
    out = folder / "out"
    Study.from_yaml(path).run(out, engine="inline", progress=False, best_run=False)
    return out


@pytest.fixture(scope="module")
def study_dir():
    """A finished 3 x 2 x 2 study over the object's x, y and yaw (12 placements)."""
    folder = Path(tempfile.mkdtemp(prefix="gcm-report-"))
    sweep = {"object_pose": {"x": [0.4, 0.55, 0.7], "y": [-0.15, 0.15], "yaw_deg": [0, 90]}}
    yield _run(folder, sweep)
    shutil.rmtree(folder, ignore_errors=True)


def _cells(page: str) -> dict[int, str]:
    """Placement id -> the value printed in its map cell."""
    found = re.findall(r'<g class="cell" data-pid="(\d+)">.*?<text [^>]*>([^<]*)</text></g>', page)
    return {int(pid): text for pid, text in found}


def test_a_study_writes_a_report_with_a_cell_per_placement_and_its_value(study_dir):
    page = (study_dir / "study.html").read_text(encoding="utf-8")
    rows = {int(r["id"]): r for r in _csv(study_dir)}
    cells = _cells(page)
    assert sorted(cells) == sorted(rows)  # every grid placement (no refinement here)
    for pid, text in cells.items():
        assert text == f"{float(rows[pid]['coverage']):.2f}"
    assert page.count('<svg class="panel"') == 2  # one panel per yaw
    assert "robot base" in page and "object x [m]" in page and "object y [m]" in page
    assert page.count('<tr data-pid="') == len(rows)
    assert "<script src=" not in page and "http://" not in page.split("<script>")[0]


def _csv(study_dir: Path) -> list[dict]:
    with open(study_dir / "placements.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def test_gcm_plot_on_a_study_directory_writes_the_map_and_the_report(study_dir, tmp_path, capsys):
    out = tmp_path / "copy"
    shutil.copytree(study_dir, out)
    (out / "study.html").unlink()
    (out / "coverage.png").unlink()
    assert main(["plot", str(out)]) == 0
    printed = capsys.readouterr().out.split()
    assert printed == [str(out / "coverage.png"), str(out / "study.html")]
    assert (out / "coverage.png").read_bytes()[:4] == b"\x89PNG"
    assert _cells((out / "study.html").read_text()) == _cells(
        (study_dir / "study.html").read_text()
    )


def test_a_study_directory_without_parts_is_refused_in_one_line(study_dir, tmp_path, capsys):
    out = tmp_path / "copy"
    shutil.copytree(study_dir, out)
    shutil.rmtree(out / "placements")
    (out / "study.html").unlink()
    code = main(["plot", str(out)])
    assert_one_line_error(code, capsys.readouterr().err, "no placements/ folder", str(out))
    assert not (out / "study.html").exists()
    assert not list(out.glob(".*study.html*"))  # no temporary file left either


def test_a_tampered_part_is_skipped_with_one_warning_and_its_cell_says_missing(
    study_dir, tmp_path, capsys
):
    out = tmp_path / "copy"
    shutil.copytree(study_dir, out)
    cut = out / "placements" / "000003.npz"
    cut.write_bytes(cut.read_bytes()[:2000])  # truncated
    wrong = out / "placements" / "000005.npz"
    arrays = dict(np.load(wrong))
    arrays["metric"] = arrays["metric"][:3]  # an array of another length
    with open(wrong, "wb") as fh:
        np.savez(fh, **arrays)
    assert main(["plot", str(out)]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if line]
    assert len(warnings) == 2
    assert str(cut) in warnings[0] and str(wrong) in warnings[1]
    assert "metric 3" in warnings[1]
    cells = _cells((out / "study.html").read_text())
    assert cells[3] == cells[5] == "missing"
    assert sum(v == "missing" for v in cells.values()) == 2


def test_a_study_that_reaches_nothing_still_renders_and_says_so(tmp_path):
    out = _run(tmp_path, {"object_pose": {"x": [0.97], "y": [-0.9, 0.9]}})
    page = (out / "study.html").read_text()
    assert set(_cells(page).values()) == {"0.00"}
    assert "No placement reaches any grasp" in page


# ------------------------------------------------------------------ in a browser


def _expected(study_dir: Path, pid: int) -> tuple[np.ndarray, int]:
    """The object pose of placement ``pid`` (from its part) and its reachable count."""
    part = np.load(study_dir / "placements" / f"{pid:06d}.npz")
    world = pose_matrices(part["pose"][:1])[0] @ np.linalg.inv(
        pose_matrices(part["pose_object"][:1])[0]
    )
    reach = np.load(study_dir / "reachability.npz")
    row = int(np.flatnonzero(reach["placement_id"] == pid)[0])
    return world, int(reach["reachable"][row].sum())


def test_clicking_a_cell_loads_that_placements_scene(study_dir, tmp_path):
    page_path = study_dir / "study.html"
    with Page(tmp_path / "profile", size=(1100, 700)) as page:
        page.open(page_path)
        page.wait_for("window.studyReady === true", timeout_s=40)
        best = json.loads((study_dir / "summary.json").read_text())["best"]["id"]
        assert page.eval("document.body.dataset.selected") == str(best)
        # the placement with the lowest coverage that is not the best one
        rows = sorted(_csv(study_dir), key=lambda r: float(r["coverage"]))
        pid = int(rows[0]["id"])
        assert pid != best
        page.eval(f"document.querySelector('.cell[data-pid=\"{pid}\"]').scrollIntoView()")
        box = page.eval(
            f"(() => {{ var b = document.querySelector('.cell[data-pid=\"{pid}\"] rect')"
            ".getBoundingClientRect(); return [b.x + b.width / 2, b.y + b.height / 2]; })()"
        )
        page.click(*box)
        page.wait_for(f"document.body.dataset.selected === '{pid}'", timeout_s=10)
        want_pose, want_reachable = _expected(study_dir, pid)
        shown = page.eval("window.studyShown")
        assert shown == {"id": pid, "reachable": want_reachable}
        # the coloured glyphs: count of grasps painted in the reachable colour
        painted = page.eval(
            "(() => { var o = D.objects[0];"
            " var a = node(o.path + '/<object>').object.geometry.attributes.color;"
            " var per = a.count / o.n, rgb = D.classes[0].rgb, n = 0;"
            " for (var g = 0; g < o.n; g++) { var i = 3 * g * per;"
            "   if ([0, 1, 2].every(c => Math.abs(a.array[i + c] - rgb[c]) < 1e-6)) n++; }"
            " return n; })()"
        )
        assert painted == want_reachable
        # three.js's transforms of the object and the robot base (composed as a frame would)
        matrix = "(o => { o.updateMatrix(); return Array.from(o.matrix.elements); })"
        got = np.array(page.eval(f"{matrix}(node('object').object)")).reshape(4, 4, order="F")
        np.testing.assert_allclose(got, want_pose, atol=1e-5)
        base = np.array(page.eval(f"{matrix}(node('robot').object)")).reshape(4, 4, order="F")
        np.testing.assert_allclose(base, np.eye(4), atol=1e-6)  # the study moves the object
        # no layer of the best placement left behind where the object was (its painted skin)
        tops = page.eval('Object.keys(viewer.scene_tree.find(["meshcat"]).children)')
        assert "object" in tops and "object_reachability" not in tops
        # the table row is highlighted with the cell, and sorting keeps it
        assert page.eval(f"document.querySelector('tr[data-pid=\"{pid}\"]').className") == "sel"
        cov = {int(r["id"]): float(r["coverage"]) for r in rows}
        metric = {int(r["id"]): float(r["best_metric"] or "nan") for r in rows}
        for key, values in (("coverage", cov), ("best_metric", metric)):
            for want in (max, min):  # first click: descending, second: ascending
                page.eval(f"document.querySelector('#placements th[data-key=\"{key}\"]').click()")
                top = int(page.eval("document.querySelector('#placements tbody tr').dataset.pid"))
                finite = [v for v in values.values() if np.isfinite(v)]
                assert values[top] == want(finite), (key, want)
        page.screenshot(tmp_path / "study_report.png")
        assert page.errors == []


EVIL = '<img src=x onerror="window.PWNED=1"><!--<script>'


def test_names_with_markup_are_shown_as_text_not_run(study_dir, tmp_path):
    """An object name and a directory name with markup or placeholders stay text."""
    out = tmp_path / "s%DATA%x"
    shutil.copytree(study_dir, out)
    rows = _csv(out)
    rows[1]["object"] = EVIL  # its part is gone: the page takes the name from the CSV
    (out / "placements" / f"{int(rows[1]['id']):06d}.npz").unlink()
    with open(out / "placements.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    assert main(["plot", str(out)]) == 0
    pid = int(rows[1]["id"])
    with Page(tmp_path / "profile", size=(800, 500)) as page:
        page.open(out / "study.html")
        page.wait_for("window.studyReady === true", timeout_s=40)
        assert page.eval("document.title") == f"study {out.name}"
        page.eval(
            f"document.querySelector('.cell[data-pid=\"{pid}\"]').dispatchEvent("
            "new MouseEvent('click', {bubbles: true}))"
        )
        page.wait_for(f"document.body.dataset.selected === '{pid}'", timeout_s=10)
        assert EVIL in page.eval("document.getElementById('info').textContent")
        assert page.eval("document.querySelectorAll('img').length") == 0
        assert page.eval("window.PWNED === undefined")
        assert page.errors == []


def _page_data(page: str) -> dict:
    start = page.index('<script id="study-data" type="application/json">')
    text = page[page.index(">", start) + 1 : page.index("</script>", start)]
    return json.loads(text.replace("<\\/", "</"))


def test_a_base_sweep_places_the_robot_of_each_placement_as_its_config_does(tmp_path):
    from gcm_pipeline.study import load_study

    sweep = {"base_pose": {"x": [0.0, -0.1], "y": [0.0, 0.1], "yaw_deg": [0, 30]}}
    out = _run(tmp_path, sweep)
    page = (out / "study.html").read_text()
    assert "robot base x [m]" in page and ">object</text>" in page  # the object marked instead
    plan = load_study(tmp_path / "study.yaml")
    records = {p["id"]: p for p in _page_data(page)["placements"]}
    assert len(records) == 8
    for placement in plan.grid():
        want = plan.resolve(placement.overrides).robot.base_pose.matrix()
        got = np.array(records[placement.id]["base"]).reshape(4, 4, order="F")
        np.testing.assert_allclose(got, want, atol=1e-6)
        assert len(records[placement.id]["links"]) == len(_page_data(page)["links"])


def test_a_report_that_cannot_be_written_warns_once_and_keeps_the_results(
    tmp_path, monkeypatch, caplog
):
    from gcm_pipeline.study import execution

    def full_disk(path):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(execution, "write_study_html", full_disk)
    out = _run(tmp_path, {"object_pose": {"x": [0.45, 0.55]}})
    assert not (out / "study.html").exists()
    for name in ("placements.csv", "reachability.npz", "summary.json", "coverage.png"):
        assert (out / name).is_file(), name
    warned = [r.getMessage() for r in caplog.records if "study.html" in r.getMessage()]
    assert warned == ["study: study.html not written: [Errno 28] No space left on device"]


def test_each_object_of_a_study_is_shown_with_its_own_shape_and_grasps(tmp_path):
    can = {"shape": "cylinder", "dims": {"radius": 0.033, "height": 0.12}}
    sweep = {
        "object_pose": {"x": [0.45, 0.55]},
        "objects": [
            {"name": "bottle"},
            {"name": "can", "object": can, "set": ["candidates.count=12"]},
        ],
    }
    out = _run(tmp_path, sweep)
    page_path = out / "study.html"
    data = _page_data(page_path.read_text())
    objects = {o["name"]: o for o in data["objects"]}
    assert set(objects) == {"bottle", "can"} and all(o["shape"] for o in objects.values())
    can_id = next(p["id"] for p in data["placements"] if p["object"] == "can")
    with Page(tmp_path / "profile", size=(900, 600)) as page:
        page.open(page_path)
        page.wait_for("window.studyReady === true", timeout_s=40)
        page.eval(f"selectPlacement({can_id})")
        visible = page.eval(
            "D.objects.map(o => [o.name, node(o.shape).object.visible,"
            " node(o.path).object.visible])"
        )
        want_pose, want_reachable = _expected(out, can_id)
        assert page.eval("window.studyShown") == {"id": can_id, "reachable": want_reachable}
        shape = objects["can"]["shape"]
        matrix = "(o => { o.updateMatrix(); return Array.from(o.matrix.elements); })"
        got = np.array(page.eval(f"{matrix}(node('{shape}').object)")).reshape(4, 4, order="F")
        np.testing.assert_allclose(got, want_pose, atol=1e-5)
        assert page.errors == []
    assert sorted(map(tuple, visible)) == [("bottle", False, False), ("can", True, True)]


def test_a_study_whose_every_placement_failed_renders_its_failures(tmp_path):
    broken = tmp_path / "broken.npy"
    broken.write_bytes(b"\x93NUMPY this is not a grasp file")
    data = {
        "base": str(ROOT / "configs" / "from_file.yaml"),
        "set": ["densify.subdivisions=1", f"candidates.path={broken}", "publish.html=false"],
        "sweep": {"object_pose": {"x": [0.40, 0.45]}},
    }
    path = tmp_path / "study.yaml"
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    Study.from_yaml(path).run(out, engine="inline", progress=False, best_run=False)
    page = (out / "study.html").read_text()
    assert set(_cells(page).values()) == {"failed"}
    assert "no 3-D scene: no placement finished" in page
    assert "No placement reaches any grasp" in page
