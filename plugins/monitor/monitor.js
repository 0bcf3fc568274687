// stage monitor: draws what the server sends on /events (server-sent events).
// No libraries, nothing from the internet. Stage space: metres, y up.
// From above: x to the right, z down (right-handed, looking down). From the front: x right, y up.
"use strict";

(function () {
  // Kinect v2 joint order (stage/joints.py); bones as pairs of indices.
  const BONES = [[0, 1], [1, 20], [20, 2], [2, 3], [20, 4], [4, 5], [5, 6], [6, 7], [7, 21],
    [6, 22], [20, 8], [8, 9], [9, 10], [10, 11], [11, 23], [10, 24], [0, 12], [12, 13],
    [13, 14], [14, 15], [0, 16], [16, 17], [17, 18], [18, 19]];
  const HEAD = 3, HAND_LEFT = 7, HAND_RIGHT = 11;
  const PALETTE = ["#4fc3f7", "#f06292", "#aed581", "#ffb74d", "#ba68c8", "#4db6ac",
    "#fff176", "#90a4ae"];
  const HAND_COLOURS = { open: "#3ccf6e", closed: "#ff4d4d", lasso: "#4d8dff" };
  const ZONE_IDLE = "rgba(120,160,255,0.13)", ZONE_IDLE_LINE = "rgba(140,170,255,0.55)";
  const ZONE_LIT = "rgba(255,200,61,0.50)", ZONE_LIT_LINE = "#ffc83d";

  const state = { frame: null, status: null, scene: { zones: [], sections: [] },
    piece: { section: null, zones: {}, mappings: {} }, events: [] };
  const received = { frame: 0, status: 0, scene: 0, piece: 0, events: 0 };
  const perf = { draws: 0, drawMs: [], drawTimes: [], shown: 0 };
  // world bounds: only ever grow, so the picture does not jump
  const bounds = { x0: -3, x1: 3, y0: 0, y1: 2.4, z0: -3, z1: 3 };
  const views = {
    top: { canvas: document.getElementById("top"), h: (p) => p[0], v: (p) => p[2],
      range: () => [bounds.x0, bounds.x1, bounds.z0, bounds.z1], flip: false },
    front: { canvas: document.getElementById("front"), h: (p) => p[0], v: (p) => p[1],
      range: () => [bounds.x0, bounds.x1, bounds.y0, bounds.y1], flip: true },
  };
  let dirty = true;

  function grow(p, margin) {
    if (!p || p.length < 3 || !p.every(Number.isFinite)) return;
    bounds.x0 = Math.min(bounds.x0, p[0] - margin); bounds.x1 = Math.max(bounds.x1, p[0] + margin);
    bounds.y1 = Math.max(bounds.y1, p[1] + margin);
    bounds.z0 = Math.min(bounds.z0, p[2] - margin); bounds.z1 = Math.max(bounds.z1, p[2] + margin);
  }

  // world point -> canvas pixel (backing-store pixels, as getImageData uses)
  function project(name, p) {
    const view = views[name], c = view.canvas, pad = 24;
    const [h0, h1, v0, v1] = view.range();
    const s = Math.min((c.width - 2 * pad) / (h1 - h0), (c.height - 2 * pad) / (v1 - v0));
    const ox = (c.width - s * (h1 - h0)) / 2, oy = (c.height - s * (v1 - v0)) / 2;
    const x = ox + (view.h(p) - h0) * s;
    const y = view.flip ? c.height - oy - (view.v(p) - v0) * s : oy + (view.v(p) - v0) * s;
    return [x, y, s];
  }

  function drawGrid(name, ctx) {
    const c = views[name].canvas;
    ctx.fillStyle = "#0e1013"; ctx.fillRect(0, 0, c.width, c.height);
    ctx.strokeStyle = "#23272e"; ctx.lineWidth = 1; ctx.font = "11px sans-serif";
    ctx.fillStyle = "#596070";
    const [h0, h1, v0, v1] = views[name].range();
    for (let h = Math.ceil(h0); h <= h1; h++) {
      const a = project(name, name === "top" ? [h, 0, v0] : [h, v0, 0]);
      const b = project(name, name === "top" ? [h, 0, v1] : [h, v1, 0]);
      ctx.beginPath(); ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0], b[1]); ctx.stroke();
      ctx.fillText(h + " m", a[0] + 2, name === "top" ? a[1] + 11 : a[1] - 3);
    }
    for (let v = Math.ceil(v0); v <= v1; v++) {
      const a = project(name, name === "top" ? [h0, 0, v] : [h0, v, 0]);
      const b = project(name, name === "top" ? [h1, 0, v] : [h1, v, 0]);
      ctx.beginPath(); ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0], b[1]); ctx.stroke();
    }
    const o = project(name, [0, 0, 0]);   // the stage origin
    ctx.strokeStyle = "#3a404b"; ctx.beginPath();
    ctx.arc(o[0], o[1], 4, 0, 2 * Math.PI); ctx.stroke();
  }

  function zoneShape(name, ctx, z) {
    // a path for the zone's outline in this view; false when it cannot be drawn
    ctx.beginPath();
    if (z.shape === "box") {
      const a = project(name, z.min), b = project(name, z.max);
      ctx.rect(Math.min(a[0], b[0]), Math.min(a[1], b[1]), Math.abs(b[0] - a[0]),
        Math.abs(b[1] - a[1]));
    } else if (z.shape === "cylinder") {
      const c = z.centre;
      if (name === "top") {
        const p = project(name, c);
        ctx.arc(p[0], p[1], z.radius * p[2], 0, 2 * Math.PI);
      } else {
        const a = project(name, [c[0] - z.radius, z.y0, c[2]]);
        const b = project(name, [c[0] + z.radius, z.y1, c[2]]);
        ctx.rect(a[0], b[1], b[0] - a[0], a[1] - b[1]);
      }
    } else if (z.shape === "sphere") {
      const p = project(name, z.centre);
      ctx.arc(p[0], p[1], z.radius * p[2], 0, 2 * Math.PI);
    } else {
      return false;
    }
    return true;
  }

  function drawZones(name, ctx) {
    for (const z of state.scene.zones) {
      if (!zoneShape(name, ctx, z)) continue;
      const lit = Object.prototype.hasOwnProperty.call(state.piece.zones || {}, z.name);
      ctx.fillStyle = lit ? ZONE_LIT : ZONE_IDLE; ctx.fill();
      ctx.strokeStyle = lit ? ZONE_LIT_LINE : ZONE_IDLE_LINE; ctx.lineWidth = lit ? 3 : 1;
      ctx.stroke();
      const anchor = z.shape === "box" ? z.min : z.centre;
      const p = project(name, name === "top" ? anchor : [anchor[0], z.shape === "box" ? z.max[1]
        : (z.y1 !== undefined ? z.y1 : anchor[1] + z.radius), anchor[2]]);
      ctx.fillStyle = lit ? "#ffe08a" : "#8fa6d8"; ctx.font = (lit ? "bold " : "") + "12px sans-serif";
      ctx.fillText(z.name, p[0] + 3, p[1] - 4);
    }
  }

  function drawSensors(name, ctx) {
    const sensors = (state.status && state.status.sensors) || [];
    for (const s of sensors) {
      if (!s.position) continue;
      const p = project(name, s.position);
      ctx.fillStyle = s.ok ? "#3ccf6e" : "#ff4d4d";
      ctx.beginPath(); ctx.moveTo(p[0], p[1] - 8); ctx.lineTo(p[0] + 7, p[1] + 6);
      ctx.lineTo(p[0] - 7, p[1] + 6); ctx.closePath(); ctx.fill();
      ctx.font = "11px sans-serif"; ctx.fillText(s.id, p[0] + 9, p[1] + 4);
    }
  }

  function drawBodies(name, ctx) {
    const frame = state.frame;
    if (!frame) return;
    for (const b of frame.bodies) {
      const colour = PALETTE[(b.id - 1) % PALETTE.length];
      const pts = b.joints.map((j) => project(name, j));
      ctx.strokeStyle = colour; ctx.lineCap = "round";
      for (const [i, k] of BONES) {
        if (!(b.conf[i] > 0 && b.conf[k] > 0)) continue;  // never-seen joints sit at the origin
        ctx.globalAlpha = Math.min(b.conf[i], b.conf[k]) < 1 ? 0.55 : 1;
        ctx.lineWidth = 3;
        ctx.beginPath(); ctx.moveTo(pts[i][0], pts[i][1]); ctx.lineTo(pts[k][0], pts[k][1]);
        ctx.stroke();
      }
      ctx.globalAlpha = 1;
      const head = pts[HEAD];
      ctx.fillStyle = colour; ctx.beginPath();
      ctx.arc(head[0], head[1], Math.max(4, 0.11 * head[2]), 0, 2 * Math.PI); ctx.fill();
      [[HAND_LEFT, 0], [HAND_RIGHT, 1]].forEach(([j, hand]) => {
        if (!(b.conf[j] > 0)) return;
        ctx.fillStyle = HAND_COLOURS[b.hands[hand]] || "#9aa0a6";
        ctx.beginPath(); ctx.arc(pts[j][0], pts[j][1], 5, 0, 2 * Math.PI); ctx.fill();
      });
      ctx.fillStyle = "#ffffff"; ctx.font = "bold 13px sans-serif";
      ctx.fillText(String(b.id), head[0] + 9, head[1] - 8);
    }
  }

  function draw() {
    const t0 = performance.now();
    if (state.frame) for (const b of state.frame.bodies) grow(b.position, 1.0);
    for (const name of Object.keys(views)) {
      const ctx = views[name].canvas.getContext("2d");
      drawGrid(name, ctx); drawZones(name, ctx); drawSensors(name, ctx); drawBodies(name, ctx);
    }
    const ms = performance.now() - t0;
    perf.draws += 1; perf.drawMs.push(ms); perf.drawTimes.push(t0);
    if (perf.drawMs.length > 600) { perf.drawMs.shift(); perf.drawTimes.shift(); }
    if (t0 - perf.shown > 500) {  // the page's own frame rate, over the last second
      perf.shown = t0;
      text("draw-fps", String(perf.drawTimes.filter((t) => t > t0 - 1000).length));
    }
  }

  function loop() {
    if (dirty) { dirty = false; draw(); }
    requestAnimationFrame(loop);
  }

  // ---------------------------------------------------------------- side panel
  function text(id, value) { const el = document.getElementById(id); if (el) el.textContent = value; }
  function el(tag, attrs, children) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (k === "class") e.className = v; else if (k === "title") e.title = v; else e.setAttribute(k, v);
    }
    for (const c of children || []) e.append(c instanceof Node ? c : document.createTextNode(String(c)));
    return e;
  }

  function fmt(v, digits) { return v === null || v === undefined ? "–" : Number(v).toFixed(digits); }

  function renderStatus() {
    const s = state.status;
    const body = document.querySelector("#sensors tbody");
    body.replaceChildren(...s.sensors.map((x) => el("tr", { class: x.ok ? "ok" : "bad",
      "data-sensor": x.id, title: x.position ? "at " + x.position.map((v) => v.toFixed(2)).join(", ") + " m" : "" }, [
      el("td", {}, [x.id]), el("td", {}, [fmt(x.fps, 0)]), el("td", {}, [fmt(x.fitness, 2)]),
      el("td", { class: "reason" }, [x.ok ? (x.state || "ok") : x.reason])])));
    if (!s.sensors.length) body.replaceChildren(el("tr", {}, [el("td", { class: "none", colspan: 4 }, ["no sensor yet"])]));
    const e = s.engine;
    const rows = [["engine drops", e.drops_total]];
    for (const [reason, n] of Object.entries(e.drops || {})) rows.push(["  " + reason, n]);
    rows.push(["view drops", s.view_drops]);
    for (const [name, v] of Object.entries(s.views || {})) {
      if (v.frames_dropped || v.events_dropped || v.state !== "running") {
        rows.push(["  " + name + (v.state !== "running" ? " (" + v.state + ")" : ""),
          v.frames_dropped + v.events_dropped]);
      }
    }
    const lat = e.latency_ms || {};
    if (lat.n) rows.push(["latency p99", lat.p99.toFixed(2) + " ms"]);
    const fc = e.forecast || {};
    for (const [h, sd] of Object.entries(fc.sd_mm || {})) {
      rows.push(["forecast " + (1000 * Number(h)).toFixed(0) + " ms", "s.d. " + sd + " mm"]);
    }
    if (fc.speed_capped || fc.bones_fixed) {
      rows.push(["forecast bounded", (fc.speed_capped || 0) + " speed, " + (fc.bones_fixed || 0) + " bones"]);
    }
    document.querySelector("#drops tbody").replaceChildren(...rows.map(([k, v]) =>
      el("tr", {}, [el("td", {}, [k]), el("td", {}, [v])])));
    text("drops-total", (e.drops_total || 0) + (s.view_drops || 0));
    renderHealth(s.health);
    for (const x of s.sensors) if (x.position) grow(x.position, 0.5);
  }

  function renderHealth(h) {
    const box = document.getElementById("health");
    if (!h) return;
    const en = h.engine || {};
    const figures = [["frame p99", fmt(en.frame_ms_p99, 2) + " ms"], ["memory", fmt(en.rss_mb, 0) + " MB"],
      ["cpu", fmt(en.cpu_percent, 0) + " %"], ["kernel drops", en.kernel_drops ?? "–"]];
    const synths = Object.entries(h.synths || {}).map(([name, p]) =>
      el("li", { class: p.connected ? "ok" : "bad" }, [name + ": " + (p.connected ? "connected" : (p.reason || "reconnecting"))]));
    box.className = h.ok ? "ok" : "bad";
    box.replaceChildren(
      el("p", { class: "verdict" }, [h.ok ? "all well" : h.problems.length + " problem(s)"]),
      el("ul", { class: "problems" }, h.problems.map((p) => el("li", {}, [p]))),
      el("ul", { class: "synths" }, synths),
      el("table", {}, [el("tbody", {}, figures.map(([k, v]) => el("tr", {}, [el("td", {}, [k]), el("td", {}, [v])])))]));
  }

  function renderZones() {
    const list = document.getElementById("zones");
    const zones = state.scene.zones;
    if (!zones.length) { list.replaceChildren(el("li", { class: "none" }, ["no zones"])); return; }
    list.replaceChildren(...zones.map((z) => {
      const who = (state.piece.zones || {})[z.name];
      return el("li", { class: who ? "occupied" : "", "data-zone": z.name },
        [z.name + (who && who.length ? " (" + who.join(", ") + ")" : "")]);
    }));
  }

  function renderPiece() {
    text("section", state.piece.section || "–");
    const rows = Object.entries(state.piece.mappings || {}).map(([k, v]) =>
      el("tr", {}, [el("td", {}, [k]), el("td", {}, [Number(v).toFixed(3)])]));
    for (const [k, v] of Object.entries(state.piece.outputs || {})) {
      rows.push(el("tr", { class: "out" }, [el("td", {}, [k]), el("td", {}, [v])]));
    }
    document.querySelector("#mappings tbody").replaceChildren(...rows);
    renderZones();
  }

  function renderEvents() {
    const list = document.getElementById("events");
    list.replaceChildren(...state.events.slice(-40).reverse().map((e) =>
      el("li", { "data-type": e.type }, [el("span", { class: "t" }, [e.t.toFixed(2)]), e.text])));
  }

  // ---------------------------------------------------------------- the stream
  const handlers = {
    frame(d) { state.frame = d; text("people", d.bodies.length); text("engine-fps", d.fps.toFixed(0)); },
    status(d) { state.status = d; renderStatus(); },
    scene(d) {
      state.scene = d;
      for (const z of d.zones) {
        if (z.min) { grow(z.min, 0.3); grow(z.max, 0.3); }
        if (z.centre) grow([z.centre[0] - (z.radius || 0), z.y1 || z.centre[1], z.centre[2] - (z.radius || 0)], 0.3);
        if (z.centre) grow([z.centre[0] + (z.radius || 0), z.centre[1], z.centre[2] + (z.radius || 0)], 0.3);
      }
      renderZones();
    },
    piece(d) { state.piece = d; renderPiece(); },
    events(d) { state.events.push(...d); if (state.events.length > 200) state.events.splice(0, state.events.length - 200); renderEvents(); },
  };

  function connect() {
    const source = new EventSource("/events");
    const conn = document.getElementById("connection");
    source.onopen = () => { conn.textContent = "live"; conn.className = "chip live"; };
    source.onerror = () => { conn.textContent = "connection lost, retrying…"; conn.className = "chip down"; };
    for (const kind of Object.keys(handlers)) {
      source.addEventListener(kind, (e) => {
        try { handlers[kind](JSON.parse(e.data)); } catch (err) { console.error(kind, err); }
        received[kind] += 1; dirty = true;
      });
    }
  }

  // for tests and curious people: window.stageMonitor
  window.stageMonitor = {
    state, received, perf, bounds, project, draw,
    pixel(name, p) {  // [r, g, b, a] under a world point in a view
      const [x, y] = project(name, p);
      return Array.from(views[name].canvas.getContext("2d").getImageData(Math.round(x), Math.round(y), 1, 1).data);
    },
  };
  connect();
  requestAnimationFrame(loop);
})();
