"""The scene's layers in headless Chromium (DevTools protocol): a 2,000,000-grasp page
loads and draws within its time budget, every layer is a node of the viewer's scene
tree, the envelope starts hidden, and the painted object shows both of its colours."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from cdp import Page
from test_scene_layers import _two_sided, big_scene

from gcm_pipeline.outputs.html import write_scene_html
from gcm_pipeline.outputs.scene import SceneOptions

#: Wall time the 2,000,000-grasp page has to load and draw its grasps [s].
_BUDGET_S = 60.0

#: The grasp layers' vertex counts once every scene command has run (the page's panel
#: is built then: ``gcm.state.ready``); null before, as the layers arrive one by one.
_DRAWN = """(() => {
  if (!(window.gcm && gcm.state.ready)) return null;
  const node = viewer.scene_tree.find(["meshcat", "grasps"]);
  let glyphs = 0, points = 0;
  node.object.traverse(o => {
    const n = o.geometry && o.geometry.attributes.position
      ? o.geometry.attributes.position.count : 0;
    if (o.isLineSegments) glyphs += n;
    else if (o.isPoints) points += n;
  });
  return points > 0 ? {glyphs, points, children: Object.keys(node.children)} : null;
})()"""


def _node(path: str) -> str:
    parts = json.dumps(["meshcat", *[p for p in path.split("/") if p]])
    return f"viewer.scene_tree.find({parts})"


def test_two_million_grasps_load_and_draw_in_time(tmp_path: Path):
    page_file = tmp_path / "scene.html"
    info = big_scene(page_file, 2_000_000)
    start = time.monotonic()
    with Page(tmp_path / "profile", size=(480, 360), timeout_s=_BUDGET_S) as page:
        page.open(page_file, settle_s=0.0)
        drawn = page.wait_for(_DRAWN, timeout_s=_BUDGET_S - (time.monotonic() - start))
        print(f"\n2,000,000 grasps: loaded and drawn in {time.monotonic() - start:.1f} s")
        assert not page.errors, page.errors
        nv = len(SceneOptions().gripper.template())
        assert drawn["glyphs"] == info.lod["glyphs"] * nv
        assert drawn["points"] == info.lod["points"]
        assert set(drawn["children"]) == {"reachable", "unreachable"}
        # every layer is a node of the tree; the envelope would be hidden (no robot here)
        for layer in info.layers:
            if layer["count"]:
                assert page.eval(f"{_node(layer['path'])}.object.children.length > 0"), layer


def test_envelope_hidden_and_paint_drawn(tmp_path: Path, panda):
    from PIL import Image

    box, grasps = _two_sided()
    options = SceneOptions(object=box, table=None)
    page_file = tmp_path / "scene.html"
    info = write_scene_html(page_file, grasps, None, panda, options)
    with Page(tmp_path / "profile", size=(480, 360)) as page:
        page.open(page_file)
        page.wait_for(f"{_node('/object_reachability')}.object.children.length > 0")
        assert page.eval(f"{_node('/envelope')}.object.visible") is False
        assert page.eval(f"{_node('/envelope/points')}.object.children.length") == 1
        assert page.eval(f"{_node('/object_reachability')}.object.visible") is True
        # only the painted object: hide every other layer, look at the box from the front
        for layer in info.layers:
            if layer["path"] != "/object_reachability":
                page.eval(f"{_node(layer['path'])}.set_property('visible', false)")
        for default in ("Axes", "Grid"):  # meshcat's own (red, green, blue lines)
            page.eval(f"viewer.scene_tree.find([{default!r}]).set_property('visible', false)")
        page.eval("viewer.set_dirty()")
        time.sleep(1.0)
        png = page.screenshot(tmp_path / "paint.png")
    img = np.asarray(Image.open(png).convert("RGB")).astype(int)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    red = (r > b + 60) & (r > g + 40)
    blue = (b > r + 60) & (b > g + 10)
    assert red.sum() > 200 and blue.sum() > 200, (red.sum(), blue.sum())
