// The side panel of scene.html: legend and layer toggles, top-k list, picking and the
// arm's motion (gcm_pipeline.outputs.scene_page). Reads the JSON of <script id="gcm-data">;
// drives meshcat's global `viewer`. Everything the tests read is on `window.gcm`.
(function () {
  "use strict";

  var THREE = MeshCat.THREE;
  var D = null;
  var state = { selected: null, playing: false, posed: null, rejected: false, ready: false };
  var G = {}; // the pickable grasps, decoded

  // -- data ---------------------------------------------------------------------------

  function decode(a) {
    if (!a) return null;
    var bin = atob(a.b64);
    var buf = new ArrayBuffer(bin.length);
    var u8 = new Uint8Array(buf);
    for (var i = 0; i < bin.length; i++) u8[i] = bin.charCodeAt(i);
    var data = a.dtype === "<f8" ? new Float64Array(buf) : new Float32Array(buf);
    return { data: data, width: a.shape.length > 1 ? a.shape[1] : 1 };
  }

  function rowOf(arr, k) {
    if (!arr || arr.width === 0) return null;
    var out = Array.prototype.slice.call(arr.data.subarray(k * arr.width, (k + 1) * arr.width));
    for (var i = 0; i < out.length; i++) if (!isFinite(out[i])) return null;
    return out;
  }

  function el(tag, attrs, text) {
    var e = document.createElement(tag);
    if (attrs) for (var k in attrs) e.setAttribute(k, attrs[k]);
    if (text !== undefined && text !== null) e.textContent = String(text);
    return e;
  }

  function fmt(v, digits) {
    if (v === null || v === undefined || !isFinite(v)) return "–";
    var a = Math.abs(v);
    if (a !== 0 && (a < 1e-3 || a >= 1e4)) return v.toExponential(2);
    return v.toFixed(digits === undefined ? 4 : digits);
  }

  function meshcatPath(path) {
    return ["meshcat"].concat(path.split("/").filter(function (s) { return s.length; }));
  }

  // -- forward kinematics (4 x 4 row-major) -------------------------------------------

  function mul(a, b) {
    var o = new Array(16);
    for (var i = 0; i < 4; i++) {
      for (var j = 0; j < 4; j++) {
        var s = 0;
        for (var k = 0; k < 4; k++) s += a[4 * i + k] * b[4 * k + j];
        o[4 * i + j] = s;
      }
    }
    return o;
  }

  var EYE = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];

  function motion(joint, q) {
    var x = joint.axis[0], y = joint.axis[1], z = joint.axis[2];
    if (joint.kind === "prismatic") {
      var d = q[joint.idx_q];
      return [1, 0, 0, x * d, 0, 1, 0, y * d, 0, 0, 1, z * d, 0, 0, 0, 1];
    }
    var th = joint.kind === "continuous"
      ? Math.atan2(q[joint.idx_q + 1], q[joint.idx_q])
      : q[joint.idx_q];
    var c = Math.cos(th), s = Math.sin(th), t = 1 - c;
    return [
      t * x * x + c, t * x * y - s * z, t * x * z + s * y, 0,
      t * x * y + s * z, t * y * y + c, t * y * z - s * x, 0,
      t * x * z - s * y, t * y * z + s * x, t * z * z + c, 0,
      0, 0, 0, 1,
    ];
  }

  function fk(q) {
    var kin = D.kinematics;
    var oMi = [EYE];
    for (var j = 0; j < kin.joints.length; j++) {
      var J = kin.joints[j];
      oMi.push(mul(oMi[J.parent], mul(J.placement, motion(J, q))));
    }
    return oMi;
  }

  function placements(q) {
    var oMi = fk(q);
    return D.kinematics.visuals.map(function (v) {
      var m = mul(oMi[v.joint], v.placement);
      for (var r = 0; r < 3; r++) for (var c = 0; c < 3; c++) m[4 * r + c] *= v.scale[c];
      return [v.path, m];
    });
  }

  function toolPose(q) {
    var tool = D.kinematics.tool;
    if (!tool) return null;
    return mul(fk(q)[tool.joint], tool.placement);
  }

  function canPose() {
    return !!(D.kinematics && D.kinematics.unsupported.length === 0);
  }

  // a robot whose joints the page cannot move: placements computed by Pinocchio (rows k)
  function poseFallback(k) {
    var fb = G.fallback;
    if (!fb || k >= fb.data.length / fb.width) return false;
    var base = k * fb.width;
    if (!isFinite(fb.data[base])) return false;
    D.kinematics.visuals.forEach(function (v, i) {
      var o = base + 16 * i, col = new Array(16);
      for (var r = 0; r < 4; r++) for (var c = 0; c < 4; c++) col[4 * c + r] = fb.data[o + 4 * r + c];
      viewer.set_transform(meshcatPath(v.path), col);
    });
    viewer.set_dirty();
    return true;
  }

  function pose(q) {
    if (!canPose() || !q) return false;
    placements(q).forEach(function (pm) {
      var m = pm[1], col = new Array(16);
      for (var r = 0; r < 4; r++) for (var c = 0; c < 4; c++) col[4 * c + r] = m[4 * r + c];
      viewer.set_transform(meshcatPath(pm[0]), col);
    });
    state.posed = q.slice();
    viewer.set_dirty();
    return true;
  }

  // -- the motion of one grasp --------------------------------------------------------

  var MOVE_S = 0.6, HOLD_S = 0.4, REST_S = 0.25;
  var motionTimer = null;

  function near(a, b) {
    if (!a || !b) return false;
    var m = 0;
    for (var i = 0; i < a.length; i++) m = Math.max(m, Math.abs(a[i] - b[i]));
    return m <= D.blend_limit;
  }

  function lerp(a, b, s) {
    return a.map(function (v, i) { return v + (b[i] - v) * s; });
  }

  // [t0, t1, qa, qb]: joint-space line qa -> qb over [t0, t1] [s]; a cut is a zero-length step
  function motionPlan(q, pre, ret) {
    var plan = [], t = 0;
    if (pre) {
      plan.push([t, t + REST_S, pre, pre]);
      t += REST_S;
      plan.push([t, t + (near(pre, q) ? MOVE_S : 0), near(pre, q) ? pre : q, q]);
      t += near(pre, q) ? MOVE_S : 0;
    }
    plan.push([t, t + HOLD_S, q, q]);
    t += HOLD_S;
    if (ret && near(ret, q)) {
      plan.push([t, t + MOVE_S, q, ret]);
      t += MOVE_S;
      plan.push([t, t + REST_S, ret, ret]);
      t += REST_S;
    }
    plan.push([t, t, q, q]); // rest at the grasp
    return plan;
  }

  function stopMotion() {
    if (motionTimer !== null) cancelAnimationFrame(motionTimer);
    motionTimer = null;
    state.playing = false;
  }

  function playMotion(q, pre, ret) {
    stopMotion();
    var plan = motionPlan(q, pre, ret);
    var end = plan[plan.length - 1][1];
    if (plan.length <= 2 && !pre) { pose(q); return; }
    state.playing = true;
    var t0 = performance.now();
    function step(now) {
      var t = (now - t0) / 1000;
      if (t >= end) { pose(q); stopMotion(); return; }
      for (var i = 0; i < plan.length; i++) {
        var p = plan[i];
        if (t < p[1] || i === plan.length - 1) {
          var s = p[1] > p[0] ? Math.min(1, Math.max(0, (t - p[0]) / (p[1] - p[0]))) : 1;
          pose(lerp(p[2], p[3], s));
          break;
        }
      }
      motionTimer = requestAnimationFrame(step);
    }
    motionTimer = requestAnimationFrame(step);
  }

  // -- selection and details ----------------------------------------------------------

  var marker = null;

  function worldToThree(p) {
    var root = viewer.scene_tree.find(["meshcat"]).object;
    root.updateMatrixWorld(true);
    return new THREE.Vector3(p[0], p[1], p[2]).applyMatrix4(root.matrixWorld);
  }

  function position(k) {
    var d = G.position.data;
    return [d[3 * k], d[3 * k + 1], d[3 * k + 2]];
  }

  function showMarker(k) {
    // under meshcat's root, in the world's own (z-up) coordinates
    if (!marker) {
      marker = new THREE.Mesh(
        new THREE.SphereGeometry(0.01, 16, 12),
        new THREE.MeshBasicMaterial({ color: 0xff00ff, depthTest: false, transparent: true, opacity: 0.95 })
      );
      marker.renderOrder = 10;
      viewer.scene_tree.find(["meshcat"]).object.add(marker);
    }
    var p = position(k);
    marker.position.set(p[0], p[1], p[2]);
    marker.visible = true;
  }

  function detailRow(table, key, value, cls) {
    var tr = el("tr");
    tr.appendChild(el("td", null, key));
    var td = el("td", cls ? { class: cls } : null, value);
    tr.appendChild(td);
    table.appendChild(tr);
  }

  function select(k, play) {
    var box = document.getElementById("gcm-details");
    box.textContent = "";
    if (k === null || k < 0 || k >= G.n) return false;
    state.selected = k;
    state.rejected = false;
    var reach = D.grasps.reachable[k];
    var table = el("table");
    detailRow(table, "row", D.grasps.row[k]);
    if (D.grasps.rank) detailRow(table, "rank", reach ? D.grasps.rank[k] : "–");
    detailRow(table, "reachable", reach ? "yes" : "no");
    if (!reach) detailRow(table, "reason", D.grasps.reason[k]);
    if (D.grasps.manipulability) detailRow(table, "manipulability", fmt(D.grasps.manipulability[k]));
    if (D.grasps.clearance) detailRow(table, "clearance", fmt(D.grasps.clearance[k], 4) + " m");
    var p = position(k);
    detailRow(table, "position", p.map(function (v) { return v.toFixed(3); }).join(", ") + " m");
    var q = reach ? rowOf(G.q, k) : null;
    var pre = reach ? rowOf(G.q_pregrasp, k) : null;
    var ret = reach ? rowOf(G.q_retreat, k) : null;
    if (reach) {
      detailRow(table, "approach", pre ? "q_pregrasp -> q" : "none");
      detailRow(table, "retreat", ret ? "q -> q_retreat" : "none");
    }
    var rejected = !reach ? rowOf(G.q_rejected, k - G.nReach) : null;
    var posed = false;
    if (q && !canPose()) {
      stopMotion();
      posed = poseFallback(k);
      if (posed) {
        state.posed = q.slice();
        detailRow(table, "arm", "posed from precomputed placements, without motion");
      }
    } else if (q) {
      posed = pose(q);
      if (posed && play !== false) playMotion(q, pre, ret);
    } else if (rejected) {
      stopMotion();
      posed = pose(rejected);
      state.rejected = posed;
      if (posed) detailRow(table, "arm", "rejected solution (" + D.grasps.reason[k] + "): not a valid grasp", "gcm-rejected");
    } else {
      stopMotion();
    }
    if (!posed && (q || rejected)) {
      detailRow(table, "arm", D.kinematics
        ? "not posed: joint types " + D.kinematics.unsupported.join(", ") + " are not supported here" +
          " (only the " + D.fallback_limit + " best grasps are)"
        : "not posed: the scene has no robot");
    } else if (!q && !rejected) {
      detailRow(table, "arm", reach ? "not posed: no configuration in the table" : "not posed");
    }
    if (posed && viewer.animator) viewer.animator.pause();
    box.appendChild(table);
    showMarker(k);
    var items = document.querySelectorAll("#gcm-topk-list li");
    for (var i = 0; i < items.length; i++) {
      items[i].classList.toggle("gcm-selected", Number(items[i].dataset.k) === k);
    }
    viewer.set_dirty();
    return posed;
  }

  // -- picking ------------------------------------------------------------------------

  function layerShown(li) {
    if (li < 0) return false;
    var node = viewer.scene_tree.find(meshcatPath(D.layers[li].path));
    for (var o = node.object; o; o = o.parent) if (!o.visible) return false;
    return true;
  }

  // screen position [CSS px] of grasp k (null: behind the camera); view from projector()
  function projector() {
    var cam = viewer.camera;
    cam.updateMatrixWorld(true);
    var root = viewer.scene_tree.find(["meshcat"]).object;
    root.updateMatrixWorld(true);
    var m = new THREE.Matrix4().multiplyMatrices(cam.projectionMatrix, cam.matrixWorldInverse);
    m.multiply(root.matrixWorld);
    var rect = viewer.renderer.domElement.getBoundingClientRect();
    var v = new THREE.Vector3();
    return function (k) {
      var p = position(k);
      v.set(p[0], p[1], p[2]).applyMatrix4(m);
      if (v.z > 1 || v.z < -1) return null;
      return [rect.left + (v.x + 1) / 2 * rect.width, rect.top + (1 - v.y) / 2 * rect.height];
    };
  }

  function project(k) {
    return projector()(k);
  }

  function pick(x, y) {
    var shown = D.layers.map(function (_, i) { return layerShown(i); });
    var best = [null, null], bestD = [Infinity, Infinity];
    var r2 = D.pick_radius_px * D.pick_radius_px;
    var proj = projector();
    for (var k = 0; k < G.n; k++) {
      var li = D.grasps.layer[k];
      if (li < 0 || !shown[li]) continue;
      var s = proj(k);
      if (!s) continue;
      var d = (s[0] - x) * (s[0] - x) + (s[1] - y) * (s[1] - y);
      var c = D.grasps.reachable[k] ? 0 : 1;
      if (d <= r2 && d < bestD[c]) { bestD[c] = d; best[c] = k; }
    }
    return best[0] !== null ? best[0] : best[1];
  }

  function onPointer(pane) {
    var down = null;
    pane.addEventListener("pointerdown", function (e) { down = [e.clientX, e.clientY]; });
    pane.addEventListener("pointerup", function (e) {
      if (!down) return;
      var moved = Math.abs(e.clientX - down[0]) + Math.abs(e.clientY - down[1]);
      down = null;
      if (moved > 4) return;
      var k = pick(e.clientX, e.clientY);
      state.lastPick = k;
      if (k !== null) select(k);
    });
  }

  // -- the panel ----------------------------------------------------------------------

  function setLayer(path, visible) {
    viewer.set_property(meshcatPath(path), "visible", visible);
    viewer.set_dirty();
  }

  function layerRow(layer) {
    var cls = "gcm-layer" + (layer.group === "scene" ? "" : " gcm-class");
    var row = el("label", {
      class: cls,
      "data-path": layer.path,
      "data-group": layer.group,
      "data-class": layer.path.replace(/^\/grasps\//, "").replace(/^unreachable\//, ""),
    });
    if (layer.count !== null && layer.count !== undefined) row.setAttribute("data-count", layer.count);
    var box = el("input", { type: "checkbox", "data-path": layer.path });
    box.checked = layer.visible !== false;
    box.addEventListener("change", function () { setLayer(layer.path, box.checked); });
    row.appendChild(box);
    var sw = el("span", { class: "gcm-swatch" });
    if (layer.color) sw.style.background = layer.color;
    else if (layer.group === "reachable") sw.style.background = "linear-gradient(90deg," + D.colorbar.stops.join(",") + ")";
    else sw.style.visibility = "hidden";
    row.appendChild(sw);
    row.appendChild(el("span", { class: "gcm-label" }, layer.label));
    if (layer.count !== null && layer.count !== undefined) row.appendChild(el("span", { class: "gcm-count" }, layer.count));
    return row;
  }

  function colorbar() {
    var cb = D.colorbar;
    var box = el("div", { id: "gcm-colorbar", title: cb.metric + " (" + cb.colormap + ")" });
    var bar = el("div", { class: "gcm-bar" });
    bar.style.background = "linear-gradient(90deg," + cb.stops.join(",") + ")";
    box.appendChild(bar);
    var range = el("div", { class: "gcm-range" });
    range.appendChild(el("span", { class: "gcm-min" }, fmt(cb.range[0])));
    range.appendChild(el("span", null, cb.metric));
    range.appendChild(el("span", { class: "gcm-max" }, fmt(cb.range[1])));
    box.appendChild(range);
    return box;
  }

  function legend(panel) {
    var sec = el("section", { id: "gcm-legend" });
    var groups = [["reachable", "Reachable"], ["unreachable", "Unreachable by reason"], ["scene", "Scene"]];
    groups.forEach(function (g) {
      var layers = D.layers.filter(function (l) { return l.group === g[0]; });
      if (!layers.length) return;
      sec.appendChild(el("h2", null, g[1]));
      layers.forEach(function (l) { sec.appendChild(layerRow(l)); });
      if (g[0] === "reachable") sec.appendChild(colorbar());
    });
    panel.appendChild(sec);
  }

  function topk(panel) {
    var sec = el("section", { id: "gcm-topk" });
    sec.appendChild(el("h2", null, "Top " + D.top_k));
    var list = el("ol", { id: "gcm-topk-list" });
    for (var k = 0; k < D.top_k; k++) {
      var li = el("li", { "data-k": k, "data-row": D.grasps.row[k] });
      li.appendChild(el("span", { class: "gcm-rank" }, D.grasps.rank ? "#" + D.grasps.rank[k] : "#" + (k + 1)));
      li.appendChild(el("span", null, "m " + fmt(D.grasps.manipulability ? D.grasps.manipulability[k] : null)));
      if (D.grasps.clearance) li.appendChild(el("span", null, "c " + fmt(D.grasps.clearance[k], 3)));
      (function (kk) { li.addEventListener("click", function () { select(kk); }); })(k);
      list.appendChild(li);
    }
    sec.appendChild(list);
    if (D.tour.length && viewer.animator) {
      var b = el("button", { id: "gcm-tour" }, "play top-k tour");
      b.addEventListener("click", function () { stopMotion(); viewer.animator.reset(); viewer.animator.play(); });
      sec.appendChild(b);
    }
    panel.appendChild(sec);
  }

  function build() {
    var panel = el("div", { id: "gcm-panel" });
    panel.appendChild(el("h1", null, "Grasps"));
    var c = D.counts;
    panel.appendChild(el("div", { id: "gcm-summary" }, c.total + " grasps, " + c.reachable + " reachable"));
    if (c.reachable === 0) panel.appendChild(el("div", { id: "gcm-empty" }, "no reachable grasp"));
    legend(panel);
    topk(panel);
    panel.appendChild(el("h2", null, "Selected grasp"));
    panel.appendChild(el("div", { id: "gcm-details" }, "click a grasp in the view or in the list"));
    var hint = "Click a grasp (within " + D.pick_radius_px + " px) to pose the arm and play its approach and retreat.";
    if (D.kinematics && D.kinematics.unsupported.length) {
      hint += " Joint types " + D.kinematics.unsupported.join(", ") + " are not supported here: the " +
        D.fallback_limit + " best grasps are posed from precomputed placements, without motion.";
    }
    panel.appendChild(el("div", { id: "gcm-hint" }, hint));
    document.body.appendChild(panel);
  }

  function data() {
    if (!D) D = JSON.parse(document.getElementById("gcm-data").textContent);
    return D;
  }

  function exists(path) {
    var node = viewer.scene_tree;
    var parts = meshcatPath(path);
    for (var i = 0; i < parts.length; i++) {
      node = node.children[parts[i]];
      if (node === undefined) return false;
    }
    return true;
  }

  // the live page: has the server sent the scene (every layer, the robot, the tour)?
  function arrived() {
    var d = data();
    if (!d.layers.every(function (l) { return exists(l.path); })) return false;
    if (d.kinematics && !d.kinematics.visuals.every(function (v) { return exists(v.path); })) return false;
    return !d.tour.length || (viewer.animator && viewer.animator.actions.length > 0);
  }

  function init() {
    if (state.ready) return;
    data();
    G.n = D.grasps.row.length;
    G.nReach = D.grasps.reachable.filter(function (r) { return r; }).length;
    G.position = decode(D.grasps.position);
    ["q", "q_pregrasp", "q_retreat", "q_rejected"].forEach(function (name) { G[name] = decode(D.grasps[name]); });
    G.fallback = D.kinematics ? decode(D.kinematics.placements) : null;
    build();
    D.layers.forEach(function (l) { if (l.visible === false) setLayer(l.path, false); });
    var pane = document.getElementById("meshcat-pane");
    onPointer(pane);
    viewer.set_3d_pane_size();
    state.ready = true;
    window.gcm.data = D;
  }

  window.gcm = {
    init: init,
    arrived: arrived,
    state: state,
    select: select,
    pick: pick,
    project: project,
    projectAll: function () {
      var proj = projector();
      var out = [];
      for (var k = 0; k < G.n; k++) out.push(proj(k));
      return out;
    },
    fk: function (q) { return fk(q); },
    placements: function (q) { return placements(q); },
    toolPose: function (q) { return toolPose(q); },
    layerShown: function (path) {
      for (var i = 0; i < D.layers.length; i++) if (D.layers[i].path === path) return layerShown(i);
      return null;
    },
    indexOfRow: function (row) { return D.grasps.row.indexOf(row); },
  };
})();
