// SPDX-License-Identifier: Apache-2.0
// magcal collect --view: the live page. Plain canvas 2D drawing, no library: an orthographic
// view of the unit sphere of field directions in the sensor's frame, turned with the mouse.
// The server (magcal/view/server.py) sends the whole state on /ws each time it changes:
//   {title, done, compasses: [panel...], result: {before, after, ...} | null}
// with each panel as magcal/view/model.py's CompassView.snapshot() builds it.
"use strict";
(function () {
  var view = { yaw: -0.7, pitch: -0.45 };  // shared by every sphere on the page, radians
  var state = null;
  var panels = {};  // panel name -> its DOM elements

  var COVERED = [26, 127, 55];
  var MISSING = "rgba(214, 58, 45, 0.55)";
  var TARGET = "#e07b00";
  var AXES = [["x", [1, 0, 0], "#c0392b"], ["y", [0, 1, 0], "#27ae60"],
              ["z", [0, 0, 1], "#2c5fd6"]];

  // The sensor frame to the screen: yaw about z, then pitch about the screen's horizontal
  // (a negative pitch looks from above +z). Returns [right, up, towards the viewer].
  function project(v) {
    var cy = Math.cos(view.yaw), sy = Math.sin(view.yaw);
    var x = cy * v[0] - sy * v[1], y = sy * v[0] + cy * v[1], z = v[2];
    var cp = Math.cos(view.pitch), sp = Math.sin(view.pitch);
    return [x, z * cp - y * sp, -(y * cp + z * sp)];
  }

  function toCanvas(ctx, p, scale) {
    var w = ctx.canvas.width, h = ctx.canvas.height;
    return [w / 2 + scale * p[0], h / 2 - scale * p[1]];
  }

  function unit(z, phi) {
    var r = Math.sqrt(Math.max(0, 1 - z * z));
    return [r * Math.cos(phi), r * Math.sin(phi), z];
  }

  // Each cell of the equal-area partition: its outline (unit vectors) and centre.
  function cellGeometry(cells) {
    var out = [], zs = cells.z_edges, counts = cells.band_counts;
    for (var b = 0; b < counts.length; b++) {
      var k = counts[b], top = zs[b], bottom = zs[b + 1];
      var steps = Math.max(2, Math.round(36 / k));
      for (var j = 0; j < k; j++) {
        var a0 = 2 * Math.PI * j / k, a1 = 2 * Math.PI * (j + 1) / k, outline = [], s;
        for (s = 0; s <= steps; s++) outline.push(unit(top, a0 + (a1 - a0) * s / steps));
        for (s = steps; s >= 0; s--) outline.push(unit(bottom, a0 + (a1 - a0) * s / steps));
        var zc = b === 0 ? 1 : (b === counts.length - 1 ? -1 : 0.5 * (top + bottom));
        out.push({ outline: outline, centre: unit(zc, 0.5 * (a0 + a1)) });
      }
    }
    return out;
  }

  function covered(count) {
    var a = 0.25 + 0.5 * Math.min(1, Math.log(1 + count) / Math.log(100));
    return "rgba(" + COVERED.join(",") + "," + a.toFixed(3) + ")";
  }

  function arrow(ctx, from, to, colour, width) {
    var dx = to[0] - from[0], dy = to[1] - from[1], len = Math.hypot(dx, dy) || 1;
    var ux = dx / len, uy = dy / len, head = Math.min(12, 0.4 * len);
    ctx.strokeStyle = colour; ctx.fillStyle = colour; ctx.lineWidth = width;
    ctx.beginPath(); ctx.moveTo(from[0], from[1]); ctx.lineTo(to[0], to[1]); ctx.stroke();
    ctx.beginPath(); ctx.moveTo(to[0], to[1]);
    ctx.lineTo(to[0] - head * ux + 0.5 * head * uy, to[1] - head * uy - 0.5 * head * ux);
    ctx.lineTo(to[0] - head * ux - 0.5 * head * uy, to[1] - head * uy + 0.5 * head * ux);
    ctx.closePath(); ctx.fill();
  }

  // A label beside the point ``at``, on the side away from ``from``.
  // Kept inside the canvas.
  function label(ctx, text, from, at) {
    var width = ctx.measureText(text).width, left = at[0] < from[0];
    var x = left ? at[0] - 6 - width : at[0] + 6;
    x = Math.max(2, Math.min(ctx.canvas.width - width - 2, x));
    var y = Math.max(12, Math.min(ctx.canvas.height - 4, at[1] + (at[1] < from[1] ? -4 : 12)));
    ctx.fillText(text, x, y);
  }

  function drawAxes(ctx, scale, length) {
    ctx.font = "13px sans-serif";
    AXES.forEach(function (a) {
      var o = toCanvas(ctx, [0, 0, 0], scale);
      var e = toCanvas(ctx, project(a[1].map(function (c) { return c * length; })), scale);
      ctx.strokeStyle = a[2]; ctx.lineWidth = 1.5;
      ctx.beginPath(); ctx.moveTo(o[0], o[1]); ctx.lineTo(e[0], e[1]); ctx.stroke();
      ctx.fillStyle = a[2]; label(ctx, "+" + a[0], o, e);
    });
  }

  function drawOutline(ctx, scale) {
    var c = toCanvas(ctx, [0, 0, 0], scale);
    ctx.strokeStyle = "#999"; ctx.lineWidth = 1;
    ctx.beginPath(); ctx.arc(c[0], c[1], scale, 0, 2 * Math.PI); ctx.stroke();
  }

  function drawDots(ctx, points, scale, front, back) {
    for (var i = 0; i < points.length; i++) {
      var p = project(points[i]), q = toCanvas(ctx, p, scale);
      ctx.fillStyle = p[2] >= 0 ? front : back;
      ctx.fillRect(q[0] - 1.5, q[1] - 1.5, 3, 3);
    }
  }

  // The live sphere: cells coloured by coverage (front half), the directions seen, the
  // sensor axes and an arrow to the largest hole.
  function drawCoverage(canvas, panel) {
    var ctx = canvas.getContext("2d"), scale = 0.36 * Math.min(canvas.width, canvas.height);
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    drawOutline(ctx, scale);
    if (panel.cells) {
      if (!canvas.cellGeometry || canvas.cellGeometry.n !== panel.counts.length) {
        canvas.cellGeometry = cellGeometry(panel.cells);
        canvas.cellGeometry.n = panel.counts.length;
      }
      canvas.cellGeometry.forEach(function (cell, i) {
        if (project(cell.centre)[2] < 0) return;  // the far side: turn the sphere to see it
        ctx.beginPath();
        cell.outline.forEach(function (v, s) {
          var q = toCanvas(ctx, project(v), scale);
          if (s === 0) ctx.moveTo(q[0], q[1]); else ctx.lineTo(q[0], q[1]);
        });
        ctx.closePath();
        ctx.fillStyle = panel.counts[i] > 0 ? covered(panel.counts[i]) : MISSING;
        ctx.fill();
        ctx.strokeStyle = "rgba(255,255,255,0.9)"; ctx.lineWidth = 1; ctx.stroke();
      });
    }
    drawDots(ctx, panel.points || [], scale, "rgba(20, 35, 90, 0.75)", "rgba(20, 35, 90, 0)");
    drawAxes(ctx, scale, 1.2);
    if (panel.target) {
      var tip = toCanvas(ctx, project(panel.target.map(function (c) { return 1.35 * c; })), scale);
      var centre = toCanvas(ctx, [0, 0, 0], scale);
      arrow(ctx, centre, tip, TARGET, 3);
      ctx.fillStyle = TARGET; ctx.font = "bold 14px sans-serif";
      label(ctx, "missing", centre, tip);
    }
  }

  // The sensor as a box, the face to turn along the field highlighted, and the arrow of
  // the field direction still missing.
  function drawSensor(canvas, panel) {
    var ctx = canvas.getContext("2d"), scale = 0.26 * Math.min(canvas.width, canvas.height);
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    var t = panel.target;
    var best = -1, bestAbs = 0;
    if (t) for (var a = 0; a < 3; a++) if (Math.abs(t[a]) > bestAbs) { bestAbs = Math.abs(t[a]); best = a; }
    var faces = [];
    for (var axis = 0; axis < 3; axis++) {
      [1, -1].forEach(function (sign) {
        var n = [0, 0, 0]; n[axis] = sign;
        var u = [0, 0, 0], v = [0, 0, 0]; u[(axis + 1) % 3] = 1; v[(axis + 2) % 3] = 1;
        var corners = [[1, 1], [1, -1], [-1, -1], [-1, 1]].map(function (c) {
          return [0, 1, 2].map(function (i) { return 0.7 * (n[i] + c[0] * u[i] + c[1] * v[i]); });
        });
        var hot = axis === best && t && Math.sign(t[axis]) === sign;
        faces.push({ n: n, corners: corners, depth: project(n)[2], hot: hot,
                     label: (sign > 0 ? "+" : "-") + "xyz"[axis] });
      });
    }
    faces.sort(function (f, g) { return f.depth - g.depth; });
    faces.forEach(function (f) {
      if (f.depth <= 0) return;
      ctx.beginPath();
      f.corners.forEach(function (c, i) {
        var q = toCanvas(ctx, project(c), scale);
        if (i === 0) ctx.moveTo(q[0], q[1]); else ctx.lineTo(q[0], q[1]);
      });
      ctx.closePath();
      ctx.fillStyle = f.hot ? "rgba(224, 123, 0, 0.85)" : "rgba(200, 205, 215, 0.9)";
      ctx.fill(); ctx.strokeStyle = "#555"; ctx.lineWidth = 1; ctx.stroke();
      var m = toCanvas(ctx, project(f.n.map(function (c) { return 0.7 * c; })), scale);
      ctx.fillStyle = "#222"; ctx.font = (f.hot ? "bold " : "") + "13px sans-serif";
      ctx.fillText(f.label, m[0] - 8, m[1] + 4);
    });
    if (t) {
      var from = toCanvas(ctx, project(t.map(function (c) { return 0.75 * c; })), scale);
      var to = toCanvas(ctx, project(t.map(function (c) { return 1.9 * c; })), scale);
      arrow(ctx, from, to, TARGET, 3);
      ctx.fillStyle = TARGET; ctx.font = "bold 13px sans-serif";
      label(ctx, "along the field", from, to);
    }
  }

  function drawCloud(canvas, points) {
    var ctx = canvas.getContext("2d");
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    var far = 1.1;
    points.forEach(function (p) { far = Math.max(far, Math.hypot(p[0], p[1], p[2])); });
    var scale = 0.42 * Math.min(canvas.width, canvas.height) / far;
    drawOutline(ctx, scale);
    drawDots(ctx, points, scale, "rgba(20, 35, 90, 0.8)", "rgba(20, 35, 90, 0.15)");
    drawAxes(ctx, scale, 1.15);
  }

  function element(tag, cls, parent) {
    var e = document.createElement(tag);
    if (cls) e.className = cls;
    if (parent) parent.appendChild(e);
    return e;
  }

  function makePanel(name) {
    var root = element("section", "panel", document.getElementById("panels"));
    root.setAttribute("data-compass", name);
    element("h2", "", root).textContent = name;
    var p = { root: root, instruction: element("p", "instruction", root) };
    var row = element("div", "row", root);
    p.sphere = element("canvas", "sphere", row); p.sphere.width = 420; p.sphere.height = 420;
    var side = element("div", "", row);
    var dl = element("dl", "", side);
    function item(label, cls) {
      element("dt", "", dl).textContent = label;
      return element("dd", cls, dl);
    }
    p.coverage = item("coverage", "big coverage");
    p.residual = item("live estimate", "residual");
    p.figures = item("received", "figures");
    p.sensor = element("canvas", "sensor", side); p.sensor.width = 240; p.sensor.height = 240;
    p.caption = element("p", "caption", side);
    [p.sphere, p.sensor].forEach(dragToTurn);
    return p;
  }

  function renderPanel(panel) {
    var p = panels[panel.name] || (panels[panel.name] = makePanel(panel.name));
    p.root.setAttribute("data-samples", panel.samples);
    p.instruction.textContent = panel.instruction;
    p.instruction.classList.toggle("ok", !!panel.ok_to_stop);
    if (panel.coverage_pct !== undefined) {
      p.coverage.textContent = panel.coverage_pct + " %";
      p.root.setAttribute("data-coverage", panel.coverage_pct);
    }
    p.residual.textContent = panel.residual || "";
    p.figures.textContent = panel.figures || "";
    p.caption.textContent = panel.face
      ? "Turn the sensor so that its " + panel.face + " side points along the field " +
        "(north and down in the northern hemisphere, north and up in the southern)."
      : (panel.ok_to_stop ? "Enough directions: you may stop." : "");
    drawCoverage(p.sphere, panel);
    drawSensor(p.sensor, panel);
  }

  function renderResult(result) {
    var section = document.getElementById("result");
    section.hidden = false;
    var text = "";
    if (result.before_spread_pct !== undefined) {
      text = "Field strength spread: " + result.before_spread_pct + " % in the raw readings";
      text += result.after_spread_pct !== undefined
        ? ", " + result.after_spread_pct + " % after the fit." : ".";
    }
    if (result.error) text += " The fit was refused: " + result.error;
    document.getElementById("result-text").textContent = text;
    drawCloud(document.getElementById("before"), result.before || []);
    drawCloud(document.getElementById("after"), result.after || []);
  }

  function render() {
    if (!state) return;
    (state.compasses || []).forEach(renderPanel);
    if (state.result) renderResult(state.result);
    var status = document.getElementById("status");
    status.setAttribute("data-status", state.done ? "done" : "collecting");
    status.textContent = state.done ? "collection ended (" + state.stopped + ")" : "collecting";
  }

  function dragToTurn(canvas) {
    var last = null;
    canvas.addEventListener("pointerdown", function (e) {
      last = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId);
    });
    canvas.addEventListener("pointermove", function (e) {
      if (!last) return;
      view.yaw += 0.01 * (e.clientX - last[0]);
      view.pitch = Math.max(-1.5, Math.min(1.5, view.pitch - 0.01 * (e.clientY - last[1])));
      last = [e.clientX, e.clientY];
      render();
    });
    ["pointerup", "pointercancel"].forEach(function (type) {
      canvas.addEventListener(type, function () { last = null; });
    });
  }
  ["before", "after"].forEach(function (id) { dragToTurn(document.getElementById(id)); });

  var socket = new WebSocket("ws://" + location.host + "/ws");
  socket.onmessage = function (event) { state = JSON.parse(event.data); render(); };
  socket.onclose = function () {
    var status = document.getElementById("status");
    if (state && state.done) {
      status.textContent += "; magcal has finished, this page no longer updates";
    } else {
      status.setAttribute("data-status", "disconnected");
      status.textContent = "disconnected from magcal";
    }
  };
})();
