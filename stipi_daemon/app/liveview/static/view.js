// The STIP-I view: state and frames over a websocket, drawn with SVG. Live, the server
// pushes the newest frame (at most 10 a second, the next only once this one has left it);
// replay, the page asks for the frame it shows ("seq:N").
// Every text from the server is set with textContent (never parsed as markup).
"use strict";
(function () {
  const token = new URLSearchParams(location.search).get("token") || "";
  const q = "token=" + encodeURIComponent(token);
  const SVG = "http://www.w3.org/2000/svg";
  const PARAMS = [
    ["depth_mm", "D_p", "mm"], ["rebound_force_n", "F_r", "N"],
    ["recovery_time_s", "T_r", "s"], ["elasticity_kpa", "E", "kPa"],
    ["tau_s", "tau", "s"], ["viscosity_n_s_per_mm2", "eta = E*T_r", "N*s/mm^2"],
    ["viscosity_from_time_constant_n_s_per_mm2", "eta_tau = E*tau", "N*s/mm^2"],
  ];
  const st = {
    info: null, force: [], sk: [], transitions: [], notes: [], now: 0, phase: "-",
    phaseSince: 0, prompt: "", t0: null, params: null, health: {}, frameSeq: null,
    shownSeq: null, fetching: false, lastFetch: 0, ws: null, step: 1, frames: [], marks: {}, cursorT: null,
    finished: false, loading: false, pending: null,
  };
  const $ = (id) => document.getElementById(id);
  const text = (id, s) => { $(id).textContent = s; };
  const fmt = (v, d) => (v === null || v === undefined || !isFinite(v)) ? "-" : Number(v).toPrecision(d || 4);

  function el(tag, attrs) {
    const e = document.createElementNS(SVG, tag);
    for (const k in attrs) e.setAttribute(k, attrs[k]);
    return e;
  }

  // ---------------------------------------------------------------- frames
  // Replay only: ask for the frame the scrubber chose, once the last one asked for came.
  function wantFrame() {
    if (!st.info || st.info.mode !== "replay") return;
    if (st.fetching && performance.now() - st.lastFetch > 2000) st.fetching = false;  // none came
    if (st.fetching || !st.ws || st.ws.readyState !== 1) return;
    if (st.frameSeq === null || st.frameSeq === st.shownSeq) return;
    st.fetching = true;
    st.lastFetch = performance.now();
    st.ws.send("seq:" + st.frameSeq);
  }

  // A frame as it comes; one that comes while the last is still being decoded waits, and
  // a newer one replaces it (latest wins).
  function gotFrame(buf) {
    if (st.loading) { st.pending = buf; return; }
    showFrame(buf);
  }

  function showFrame(buf) {
    st.loading = true;
    const n = new DataView(buf).getUint32(0);
    const f = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
    const blob = new Blob([new Uint8Array(buf, 4 + n)], { type: "image/jpeg" });
    const img = $("frame");
    const old = img.src;
    img.onload = () => {
      if (old.startsWith("blob:")) URL.revokeObjectURL(old);
      st.shownSeq = f.seq;
      st.step = f.step;
      img.dataset.seq = String(f.seq);
      drawRoi();
      st.loading = false;
      st.fetching = false;
      if (st.pending) { const next = st.pending; st.pending = null; showFrame(next); } else wantFrame();
    };
    img.onerror = img.onload;
    img.src = URL.createObjectURL(blob);
    text("frame-info", "frame " + f.seq + "   t = " + f.t_s.toFixed(3) + " s   S_k = " + f.s_k + " px");
    if (st.info && st.info.mode === "replay") { st.cursorT = f.t_s; drawTraces(); }
  }

  function drawRoi() {
    const img = $("frame"), svg = $("overlay"), info = st.info;
    if (!info || !img.naturalWidth) return;
    const step = st.step || 1;
    const w = img.naturalWidth * step, h = img.naturalHeight * step;
    svg.setAttribute("viewBox", "0 0 " + w + " " + h);
    svg.replaceChildren();
    const r = info.roi;
    if (!r) return;
    const shape = r.kind === "circle"
      ? el("circle", { cx: r.cx_px, cy: r.cy_px, r: r.radius_px, class: "roi" })
      : el("rect", { x: r.x_px, y: r.y_px, width: r.width_px, height: r.height_px, class: "roi" });
    svg.appendChild(shape);
  }

  // ---------------------------------------------------------------- traces
  function drawTrace(id, pts, label) {
    const svg = $(id), W = 600, H = 160;
    svg.replaceChildren();
    const t1 = Math.max(st.now, pts.length ? pts[pts.length - 1][0] : 0, 1e-9);
    const t0 = Math.min(pts.length ? pts[0][0] : 0, 0);
    let lo = Infinity, hi = -Infinity;
    for (const p of pts) { if (p[1] < lo) lo = p[1]; if (p[1] > hi) hi = p[1]; }
    if (!isFinite(lo)) { lo = 0; hi = 1; }
    if (hi - lo < 1e-9) { hi = lo + 1; }
    const x = (t) => ((t - t0) / (t1 - t0)) * W;
    const y = (v) => H - 4 - ((v - lo) / (hi - lo)) * (H - 8);
    const tr = st.transitions;
    for (let i = 0; i < tr.length; i++) {
      const name = tr[i][2];
      if (name !== "pitting" && name !== "recovery") continue;
      const end = i + 1 < tr.length ? tr[i + 1][0] : t1;
      svg.appendChild(el("rect", { x: x(tr[i][0]), y: 0, width: Math.max(0, x(end) - x(tr[i][0])),
        height: H, class: "phase-" + name }));
    }
    if (st.t0 !== null) svg.appendChild(el("line", { x1: x(st.t0), x2: x(st.t0), y1: 0, y2: H, class: "t0" }));
    for (const k in st.marks) {
      const m = st.marks[k];
      if (m) svg.appendChild(el("line", { x1: x(m.t_s), x2: x(m.t_s), y1: 0, y2: H, class: "mark" }));
    }
    const every = Math.max(1, Math.floor(pts.length / 1500));
    const coords = [];
    for (let i = 0; i < pts.length; i += every) coords.push(x(pts[i][0]).toFixed(1) + "," + y(pts[i][1]).toFixed(1));
    const line = el("polyline", { points: coords.join(" "), class: "line" });
    svg.appendChild(line);
    svg.dataset.points = String(pts.length);
    svg.dataset.cursorT = st.cursorT === null ? "" : String(st.cursorT);
    if (st.cursorT !== null) svg.appendChild(el("line", { x1: x(st.cursorT), x2: x(st.cursorT), y1: 0, y2: H, class: "cursor" }));
    const t = el("text", { x: 4, y: 14 });
    t.textContent = label + "  " + fmt(lo, 4) + " .. " + fmt(hi, 4);
    svg.appendChild(t);
  }

  function drawTraces() {
    drawTrace("trace-force", st.force, "force [N]");
    drawTrace("trace-sk", st.sk, "S_k [px]");
  }

  // ---------------------------------------------------------------- panels
  function countdown() {
    const info = st.info;
    if (!info || st.finished) return "";
    const total = { pitting: info.pitting_duration_s, recovery: info.recovery_max_s }[st.phase];
    if (total === undefined) return "";
    const left = Math.max(0, total - (st.now - st.phaseSince));
    return (st.phase === "pitting" ? "hold " : "recovery ") + left.toFixed(1) + " s";
  }

  function drawParams() {
    const body = $("params").tBodies[0];
    body.replaceChildren();
    const p = st.params;
    if (!p) return;
    for (const [key, sym, unit] of PARAMS) {
      const tr = document.createElement("tr");
      const status = (p.status && p.status[key]) || "ok";
      tr.dataset.quantity = key;
      tr.dataset.status = status;
      const a = document.createElement("td"); a.textContent = sym;
      const b = document.createElement("td"); b.className = "value";
      const pre = key === "recovery_time_s" && !p.settled ? ">= " : "";
      b.textContent = pre + fmt(p.values[key]) + " " + unit;
      const c = document.createElement("td"); c.className = "status"; c.textContent = status;
      tr.append(a, b, c);
      body.appendChild(tr);
    }
  }

  function drawHealth() {
    const h = st.health || {};
    const box = $("health");
    box.replaceChildren();
    for (const k of Object.keys(h)) {
      const d = document.createElement("div");
      const v = h[k];
      d.dataset.key = k;
      const shown = typeof v === "number" ? (Number.isInteger(v) ? String(v) : fmt(v, 4)) : v;
      d.textContent = k + ": " + (shown === null ? "-" : String(shown));
      if ((k === "dropped_frames" || k === "gaps" || k === "late_frames") && v > 0) d.className = "bad";
      box.appendChild(d);
    }
  }

  function showInfo(info) {
    st.info = info;
    st.force = []; st.sk = []; st.transitions = [];
    $("notes").replaceChildren();
    text("mode", info.mode === "replay" ? "replay" : "live");
    text("session", "session " + info.session_id);
    const m = info.metadata || {};
    const parts = [];
    for (const k of ["subject", "site", "operator", "note"]) if (m[k]) parts.push(k + ": " + m[k]);
    text("meta", parts.join("   "));
    if (info.mode === "replay") $("replay-controls").hidden = false;
  }

  function apply(msg) {
    if (msg.info) { showInfo(msg.info); return; }
    st.force.push(...msg.force);
    st.sk.push(...msg.s_k);
    st.transitions.push(...msg.transitions);
    for (const n of msg.notes) { const li = document.createElement("li"); li.textContent = n; $("notes").appendChild(li); }
    st.now = msg.now_s; st.phase = msg.phase; st.phaseSince = msg.phase_since_s;
    st.prompt = msg.prompt; st.t0 = msg.t_release_s; st.params = msg.params;
    st.health = msg.health; st.finished = msg.finished;
    if (msg.frames) setupReplay(msg);
    text("phase", st.phase);
    text("prompt", st.prompt);
    text("countdown", countdown());
    text("clock", "t = " + st.now.toFixed(1) + " s");
    drawParams();
    drawHealth();
    if (st.info.mode !== "replay") drawTraces();
  }

  // ---------------------------------------------------------------- replay
  function setupReplay(msg) {
    st.frames = msg.frames;
    st.marks = msg.marks || {};
    const scrub = $("scrub");
    scrub.max = String(Math.max(0, st.frames.length - 1));
    scrub.oninput = () => showIndex(+scrub.value);
    const marks = $("marks");
    marks.replaceChildren();
    for (const k of Object.keys(st.marks)) {
      const m = st.marks[k];
      if (!m) continue;
      const b = document.createElement("button");
      b.dataset.mark = k;
      b.textContent = m.label + " (frame " + m.seq + ")";
      b.onclick = () => showIndex(m.index);
      marks.appendChild(b);
    }
    const start = +(new URLSearchParams(location.search).get("frame") || 0);
    showIndex(Math.min(Math.max(0, start), st.frames.length - 1));
  }

  function showIndex(i) {
    const f = st.frames[i];
    if (!f) return;
    $("scrub").value = String(i);
    st.cursorT = f[1];
    st.frameSeq = f[0];
    drawTraces();
    wantFrame();
  }

  // ---------------------------------------------------------------- connection
  function connect() {
    const ws = new WebSocket("ws://" + location.host + "/ws?" + q);
    ws.binaryType = "arraybuffer";
    st.ws = ws;
    st.fetching = false;
    ws.onmessage = (ev) => {
      if (typeof ev.data === "string") apply(JSON.parse(ev.data)); else gotFrame(ev.data);
    };
    ws.onclose = () => {
      if (!st.finished) text("mode", (st.info ? st.info.mode : "") + " (disconnected)");
      if (!st.info || st.info.mode !== "replay") setTimeout(connect, 1000);
    };
  }
  window.addEventListener("resize", drawRoi);
  connect();
})();
