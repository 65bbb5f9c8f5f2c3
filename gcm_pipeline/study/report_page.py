"""The HTML of ``study.html``: coverage maps as SVG, the placements table, the viewer, the script.

:func:`coverage_svg` draws one SVG panel per :func:`~gcm_pipeline.study.coverage.grid_panels`
panel: a cell per grid placement coloured by coverage (viridis) with the value
printed, refined placements as filled dots, the robot base (or, when the base
is swept, the object) marked, axes in metres. Every cell, dot and table row
carries ``data-pid``; the script's ``selectPlacement(pid)`` loads that
placement into the scene and highlights it (``document.body.dataset.selected``).
"""

from __future__ import annotations

import html
import json
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gcm_pipeline.outputs.meshcat_lib import load_meshcat
from gcm_pipeline.outputs.robot_view import ROT_X90
from gcm_pipeline.study import coverage

if TYPE_CHECKING:
    from gcm_pipeline.study.report import StudyReport
    from gcm_pipeline.study.report_scene import StudyScene

__all__ = ["coverage_svg", "render_page"]

_W = 230  # plot width [px] of a panel
_M = (46, 56, 14, 40)  # margins left, right (room for the marker label), top, bottom [px]


def _esc(text: Any) -> str:
    return html.escape(str(text), quote=True)


def _viridis(value: float) -> str:
    from matplotlib import colormaps

    r, g, b, _ = colormaps["viridis"](min(max(float(value), 0.0), 1.0))
    return f"#{int(r * 255):02x}{int(g * 255):02x}{int(b * 255):02x}"


def _edges(values: Sequence[float]) -> list[float]:
    return [float(v) for v in coverage._edges(values)]  # one rule for the PNG and the page


def coverage_svg(report: StudyReport) -> str:
    """The coverage maps: one ``<svg>`` per panel (see the module docstring)."""
    rows = [r for r in report.rows if r.get("object") is not None]
    plane = coverage.plane_of(report.swept)
    if plane is None:  # nothing swept in x-y: a row of cells, one per placement
        return _strip_svg(rows)
    panels, merged = coverage.grid_panels(rows, report.swept, plane[0])
    n_objects = len({str(r["object"]) for r in rows})
    out = []
    for key, members in panels.items():
        title = f"{key[0]}, best over the rest" if merged else coverage.panel_title(key, n_objects)
        refined = [
            r
            for r in rows
            if int(r.get("round", 0)) > 0
            and str(r["object"]) == str(key[0])
            and (merged or coverage.panel_key(r, report.swept, plane[0]) == key)
        ]
        best = int(report.best["id"]) if report.best else None
        out.append(_panel_svg(title, members, refined, plane, best))
    return "\n".join(out)


def _cell_label(r: Mapping[str, Any]) -> tuple[str, str]:
    """Fill colour and printed text of a placement's cell."""
    if r.get("missing"):
        return "#c8c8c8", "missing"
    if r.get("error"):
        return "#eeeeee", "failed"
    cov = float(r.get("coverage") or 0.0)
    return _viridis(cov), f"{cov:.2f}"


def _panel_svg(
    title: str,
    members: Sequence[Mapping[str, Any]],
    refined: Sequence[Mapping[str, Any]],
    plane: tuple[str, Sequence[str]],
    best_id: int | None,
) -> str:
    pose, axes = plane
    fx = f"{pose}_{axes[0]}"
    fy = f"{pose}_{axes[1]}" if len(axes) > 1 else None
    xs = sorted({float(r[fx]) for r in members})
    ys = sorted({float(r[fy]) for r in members}) if fy else [0.0]
    ex, ey = _edges(xs), _edges(ys)
    other = "base" if pose == "object" else "object"
    spots = {
        (float(r.get(f"{other}_x") or 0.0), float(r.get(f"{other}_y") or 0.0)) for r in members
    }
    mark = next(iter(spots)) if len(spots) == 1 and fy else None
    lo_x, hi_x = min(ex[0], mark[0] if mark else ex[0]), max(ex[-1], mark[0] if mark else ex[-1])
    lo_y, hi_y = min(ey[0], mark[1] if mark else ey[0]), max(ey[-1], mark[1] if mark else ey[-1])
    pad = 0.04 * max(hi_x - lo_x, hi_y - lo_y, 1e-3)
    lo_x, hi_x, lo_y, hi_y = lo_x - pad, hi_x + pad, lo_y - pad, hi_y + pad
    s = _W / (hi_x - lo_x)
    height = (hi_y - lo_y) * s if fy else 60.0
    left, right, top, bottom = _M

    def px(x: float) -> float:
        return left + (x - lo_x) * s

    def py(y: float) -> float:
        return top + (hi_y - y) * s if fy else top + 30.0

    parts = [f'<text class="title" x="{left}" y="{top - 3}">{_esc(title)}</text>']
    cells: dict[tuple[int, int], Mapping[str, Any]] = {}
    for r in members:  # merged panels: the best placement of a cell
        k = (xs.index(float(r[fx])), ys.index(float(r[fy])) if fy else 0)
        old = cells.get(k)
        if old is None or float(r.get("coverage") or -1) > float(old.get("coverage") or -1):
            cells[k] = r
    for (j, i), r in sorted(cells.items()):
        x0, x1 = px(ex[j]), px(ex[j + 1])
        y0, y1 = (py(ey[i + 1]), py(ey[i])) if fy else (top + 10.0, top + 50.0)
        fill, text = _cell_label(r)
        dark = text not in ("missing", "failed") and float(r.get("coverage") or 0) <= 0.6
        tip = r.get("missing") or r.get("error") or f"placement {r['id']}: coverage {text}"
        parts.append(
            f'<g class="cell" data-pid="{int(r["id"])}"><title>{_esc(tip)}</title>'
            f'<rect x="{x0:.1f}" y="{y0:.1f}" width="{x1 - x0:.1f}" height="{y1 - y0:.1f}" '
            f'fill="{fill}"/><text x="{(x0 + x1) / 2:.1f}" y="{(y0 + y1) / 2 + 4:.1f}" '
            f'class="{"light" if dark else "darktext"}">{text}</text></g>'
        )
    spots = np.array([(px(float(r[fx])), py(float(r[fy]) if fy else 0.0)) for r in refined])
    radius = 6.0
    if len(spots) > 1:  # no overlap: a third of the closest two dots' distance
        gaps = np.linalg.norm(spots[:, None] - spots[None], axis=-1) + np.eye(len(spots)) * 1e9
        radius = float(np.clip(gaps.min() / 3.0, 2.0, 6.0))
    for r in refined:
        fill, text = _cell_label(r)
        parts.append(
            f'<g class="dot" data-pid="{int(r["id"])}"><title>placement {int(r["id"])} '
            f"(refined): {text}</title>"
            f'<circle cx="{px(float(r[fx])):.1f}" cy="{py(float(r[fy]) if fy else 0.0):.1f}" '
            f'r="{radius:.1f}" fill="{fill}"/></g>'
        )
    for r in [*members, *refined]:
        if int(r["id"]) == best_id:
            bx, by = px(float(r[fx])), py(float(r[fy]) if fy else 0.0)
            parts.append(
                f'<text class="best" x="{bx:.1f}" y="{by - 7:.1f}">&#9733;<title>best placement '
                f"{best_id}</title></text>"
            )
    if mark is not None:
        name = "robot base" if other == "base" else "object"
        mx, my = px(mark[0]), py(mark[1])
        parts.append(
            f'<g class="marker"><rect x="{mx - 6:.1f}" y="{my - 6:.1f}" width="12" height="12" '
            f'fill="#d62728"/><text x="{mx + 9:.1f}" y="{my - 8:.1f}">{name}</text></g>'
        )
    parts.append(_axes(px, py, xs, ys, fy, pose, axes, height))
    w, h = left + _W + right, top + height + bottom
    return f'<svg class="panel" width="{w:.0f}" height="{h:.0f}">{"".join(parts)}</svg>'


def _axes(px: Any, py: Any, xs: Sequence[float], ys: Sequence[float], fy: Any, pose: str,
          axes: Sequence[str], height: float) -> str:  # fmt: skip
    left, _, top, _ = _M
    name = "object" if pose == "object" else "robot base"
    base_y = top + height
    out = [f'<line class="axis" x1="{left}" y1="{base_y:.1f}" x2="{left + _W}" y2="{base_y:.1f}"/>']
    out += [f'<text class="tick" x="{px(x):.1f}" y="{base_y + 13:.1f}">{x:.2f}</text>' for x in xs]
    out.append(
        f'<text class="label" x="{left + _W / 2:.0f}" y="{base_y + 30:.1f}">'
        f"{name} {axes[0]} [m]</text>"
    )
    if fy:
        out.append(f'<line class="axis" x1="{left}" y1="{top}" x2="{left}" y2="{base_y:.1f}"/>')
        out += [
            f'<text class="tick ytick" x="{left - 4}" y="{py(y) + 4:.1f}">{y:.2f}</text>'
            for y in ys
        ]
        out.append(
            f'<text class="label" transform="translate(12,{top + height / 2:.0f}) rotate(-90)">'
            f"{name} {axes[1]} [m]</text>"
        )
    return "".join(out)


def _strip_svg(rows: Sequence[Mapping[str, Any]]) -> str:
    """No x-y plane swept: one cell per placement, in id order."""
    size, parts = 48, []
    for k, r in enumerate(rows):
        fill, text = _cell_label(r)
        x = 4 + k * (size + 2)
        parts.append(
            f'<g class="cell" data-pid="{int(r["id"])}"><title>placement {int(r["id"])}</title>'
            f'<rect x="{x}" y="20" width="{size}" height="{size}" fill="{fill}"/>'
            f'<text x="{x + size / 2}" y="48" class="darktext">{text}</text>'
            f'<text x="{x + size / 2}" y="14" class="tick">#{int(r["id"])}</text></g>'
        )
    width = 8 + len(rows) * (size + 2)
    return f'<svg class="panel" width="{width}" height="80">{"".join(parts)}</svg>'


def _table(report: StudyReport) -> str:
    swept = [f"{p}_{a}" for p in ("object", "base") for a in report.swept[p]]
    cols = [("id", "id"), ("object", "object"), ("round", "round")]
    cols += [(c, c.replace("_deg", " °").replace("_", " ")) for c in swept]
    cols += [
        ("coverage", "coverage"),
        ("reachable", "reachable"),
        ("best_metric", f"best {report.metric}"),
        ("mean_manipulability", "mean manip."),
        ("note", "note"),
    ]
    head = "".join(f'<th data-key="{k}">{_esc(label)}</th>' for k, label in cols)
    body = []
    for r in report.rows:
        cells = []
        for k, _ in cols:
            v = r.get(k)
            if k == "note":
                v = r.get("missing") or r.get("error") or ""
            elif k == "reachable" and v is not None:
                v = f"{int(v)} / {int(r.get('densified') or 0)}"
            elif isinstance(v, float):
                v = (
                    f"{v:.3f}"
                    if k in ("coverage", "best_metric", "mean_manipulability")
                    else f"{v:g}"
                )
            sort = r.get(k) if k not in ("note",) else v
            sort = "" if sort is None else sort
            cells.append(f'<td data-sort="{_esc(sort)}">{_esc("" if v is None else v)}</td>')
        body.append(f'<tr data-pid="{int(r["id"])}">{"".join(cells)}</tr>')
    rows = "".join(body)
    return f'<table id="placements"><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>'


def _orbit_target(scene: StudyScene) -> list[float]:
    return [float(v) for v in ROT_X90.T @ np.asarray(scene.camera_target, dtype=float)]


def render_page(report: StudyReport, scene: StudyScene, data: dict[str, Any]) -> str:
    """The whole page (self-contained: meshcat's viewer script, data, maps, table)."""
    viewer_js = ""
    if scene.commands:
        js_path = Path(load_meshcat().__file__).parent / "viewer" / "dist" / "main.min.js"
        viewer_js = js_path.read_text(encoding="utf-8")
    data = {**data, "links": scene.links, "orbit": _orbit_target(scene)}
    banner = []
    if not data["anyReachable"]:
        banner.append("No placement reaches any grasp: every cell has coverage 0.")
    if scene.message:
        banner.append(scene.message)
    banner += data["warnings"]
    best = report.best
    best_line = (
        f"best placement #{int(best['id'])} ({_esc(best['object'])}): coverage "
        f"{float(best.get('coverage') or 0):.3f}"
        if best
        else "no placement finished"
    )
    fields = {
        "TITLE": _esc(f"study {report.path.name}"),
        "HEADER": _esc(f"Study {report.path.name}") + f" — {best_line}",
        "BANNER": "".join(f"<p class='warn'>{_esc(b)}</p>" for b in banner),
        "MAPS": coverage_svg(report),
        "TABLE": _table(report),
        "VIEWERJS": viewer_js.replace("</script", "<\\/script"),
        "COMMANDS": _script_json(scene.commands),
        "DATA": _script_json(data),
        "SCRIPT": _SCRIPT,
    }
    # one pass: a field's text (a directory or object name) is never searched for placeholders
    return re.sub(r"%([A-Z]+)%", lambda m: fields.get(m.group(1), m.group(0)), _PAGE)


def _script_json(value: Any) -> str:
    """JSON for inside a <script>: every '<' escaped, so no text can close or comment it."""
    return json.dumps(value).replace("<", "\\u003c")


_PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>%TITLE%</title>
<style>
body {margin: 0; font: 13px sans-serif; display: flex; height: 100vh;}
#left {width: 50%; overflow: auto; padding: 8px; box-sizing: border-box;}
#right {width: 50%; display: flex; flex-direction: column;}
#meshcat-pane {flex: 1; position: relative; overflow: hidden; min-height: 200px;}
#info {padding: 6px; border-top: 1px solid #ccc; font-size: 12px;}
.warn {color: #a33; margin: 4px 0;}
svg.panel {margin: 4px; background: #fff;}
svg text {font-size: 10px; text-anchor: middle;}
svg text.title {text-anchor: start; font-size: 11px; font-weight: bold;}
svg text.ytick {text-anchor: end;} svg .marker text {text-anchor: start; fill: #d62728;}
svg text.light {fill: #fff;} svg text.darktext {fill: #000;}
svg .axis {stroke: #444;} svg text.best {fill: #d62728; font-size: 15px; pointer-events: none;}
.cell, .dot {cursor: pointer;} .cell rect {stroke: #fff; stroke-width: 1;}
.dot circle {stroke: #222; stroke-width: 0.4;}
.sel rect, .sel circle {stroke: #ff2d2d !important; stroke-width: 3 !important;}
table {border-collapse: collapse; margin-top: 8px; font-size: 12px;}
th, td {border: 1px solid #ddd; padding: 2px 6px; text-align: right;}
th {cursor: pointer; background: #f3f3f3;} tr {cursor: pointer;}
tr.sel td {background: #ffe2a8;}
.swatch {display: inline-block; width: 10px; height: 10px; margin: 0 3px 0 8px;}
</style></head>
<body>
<div id="left"><h3 style="margin: 4px 0">%HEADER%</h3>%BANNER%
<div id="maps">%MAPS%</div>
<p style="margin: 2px 4px">Colour: coverage (reachable fraction of the densified grasps),
0 <span class="swatch" style="background: #440154"></span> to 1
<span class="swatch" style="background: #fde725"></span>; dots: refined placements.
Click a cell, a dot or a row to load that placement's scene.</p>
%TABLE%</div>
<div id="right"><div id="meshcat-pane"></div><div id="info"></div></div>
<script>%VIEWERJS%</script>
<script id="study-data" type="application/json">%DATA%</script>
<script>
var COMMANDS = %COMMANDS%;
%SCRIPT%
</script>
</body></html>
"""

_SCRIPT = r"""
var D = JSON.parse(document.getElementById("study-data").textContent);
var byId = new Map(D.placements.map(p => [p.id, p]));
var viewer = null, lastObj = null;
function b64bytes(s) {
  var b = atob(s), u = new Uint8Array(b.length);
  for (var i = 0; i < b.length; i++) u[i] = b.charCodeAt(i);
  return u;
}
if (COMMANDS.length) {
  viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));
  COMMANDS.forEach(c => viewer.handle_command_bytearray(b64bytes(c)));
  viewer.controls.target.set(D.orbit[0], D.orbit[1], D.orbit[2]);
  viewer.controls.update();
}
function node(path) { return viewer.scene_tree.find(["meshcat"].concat(path.split("/"))); }
function setT(path, m) {
  viewer.handle_command({type: "set_transform", path: "/meshcat/" + path,
                         matrix: new Float32Array(m)});
}
function counts(p) {
  var c = new Array(D.classes.length).fill(0);
  if (p.status) b64bytes(p.status).forEach(s => c[s]++);
  return c;
}
function showPlacement(p) {
  var msg = [];
  var k = D.objects.findIndex(o => o.name === p.object);
  D.objects.forEach((o, i) => {
    var n = o.shape && node(o.shape);
    if (n) n.object.visible = (i === k);
  });
  var shape = k >= 0 ? D.objects[k].shape : "";
  if (!shape) msg.push("this object's shape is not drawn");
  if (p.obj && shape) {  // keep the object where the camera looks: move the camera with it
    if (lastObj) {
      var d = [p.obj[12] - lastObj[0], p.obj[13] - lastObj[1], p.obj[14] - lastObj[2]];
      var dv = new viewer.camera.position.constructor(d[0], d[2], -d[1]);  // z-up -> y-up
      viewer.camera.position.add(dv); viewer.controls.target.add(dv); viewer.controls.update();
    }
    lastObj = [p.obj[12], p.obj[13], p.obj[14]];
    setT(shape, p.obj);
  }
  if (p.base) { setT("robot", p.base); }
  if (p.links) p.links.forEach((m, i) => setT(D.links[i], m));
  D.objects.forEach((o, i) => {
    var n = node(o.path); if (n) n.object.visible = (i === k && p.same);
  });
  if (k >= 0 && p.same) {
    var o = D.objects[k], st = b64bytes(p.status);
    setT(o.path, p.obj);
    var attr = node(o.path + "/<object>").object.geometry.attributes.color, per = attr.count / o.n;
    for (var g = 0; g < o.n; g++) {
      var rgb = D.classes[st[g]].rgb;
      for (var v = 0; v < per; v++) attr.array.set(rgb, 3 * (g * per + v));
    }
    attr.needsUpdate = true;
  } else if (k >= 0) msg.push("its grasps differ from the object's first placement: not drawn");
  viewer.set_dirty();
  return msg;
}
function esc(s) {
  return String(s).replace(/[&<>"']/g, c => "&#" + c.charCodeAt(0) + ";");
}
function selectPlacement(pid) {
  var p = byId.get(pid);
  if (!p) return;
  document.querySelectorAll(".sel").forEach(e => e.classList.remove("sel"));
  document.querySelectorAll('[data-pid="' + pid + '"]').forEach(e => e.classList.add("sel"));
  document.body.dataset.selected = String(pid);
  var info = "placement #" + pid + " (" + esc(p.object) + ")";
  var msg = [];
  if (p.missing) msg.push(p.missing + ": not shown");
  else if (p.error) msg.push("failed: " + p.error);
  else if (viewer && p.status) {
    msg = showPlacement(p);
    info += ": coverage " + (p.coverage || 0).toFixed(3) + ", " + p.reachable + " / " +
            p.densified + " reachable";
    var c = counts(p);
    info += "<br>" + D.classes.map((k, i) => c[i] ? '<span class="swatch" style="background:rgb(' +
      k.rgb.map(x => Math.round(255 * x)).join(",") + ')"></span>' + esc(k.name) + " " + c[i] : "")
      .join("");
    window.studyShown = {id: pid, reachable: c[0]};
  } else if (D.scene) msg.push(D.scene);
  var note = msg.length ? "<br>" + esc(msg.join("; ")) : "";
  document.getElementById("info").innerHTML = info + note;
}
document.querySelectorAll("[data-pid]").forEach(e =>
  e.addEventListener("click", () => selectPlacement(Number(e.dataset.pid))));
document.querySelectorAll("#placements th").forEach((th, col) => {
  th.addEventListener("click", () => {
    var body = document.querySelector("#placements tbody");
    var dir = th.dataset.dir === "desc" ? 1 : -1;
    th.dataset.dir = dir < 0 ? "desc" : "asc";
    var rows = Array.from(body.rows);
    rows.sort((a, b) => {
      var x = a.cells[col].dataset.sort, y = b.cells[col].dataset.sort;
      var nx = parseFloat(x), ny = parseFloat(y);
      if (x === "" && y !== "") return 1;
      if (y === "" && x !== "") return -1;
      var d = (isNaN(nx) || isNaN(ny)) ? x.localeCompare(y) : nx - ny;
      return dir * d;
    });
    rows.forEach(r => body.appendChild(r));
  });
});
if (D.best !== null) selectPlacement(D.best);
window.studyReady = true;
"""
