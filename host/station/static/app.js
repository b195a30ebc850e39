// Orbitar operator station: one WebSocket to the daemon, plain JS, no library, works offline.
// Frames arrive as binary messages (header length, JSON header, JPEG) and are acknowledged once
// drawn; everything else is JSON. Motion goes through the daemon's control operations.
"use strict";

const HOLD_PERIOD_MS = 100;       // dead-man heartbeat while a jog button is held
const PING_PERIOD_MS = 2000;      // clock offset between this page and the daemon
const PING_BURST = 5;             // pings back to back after hello: a precise offset at once
const RECONNECT_MIN_MS = 500;
const RECONNECT_MAX_MS = 5000;
const TAP_SLOP_PX = 8;
const TIMING_KEEP = 300;          // frames whose latency breakdown is kept (for the benchmark)

const $ = (id) => document.getElementById(id);
const state = {
  ws: null, role: "", info: null, connected: false, token: "", refused: false,
  frames: 0, fpsTimes: [], lastLatencyMs: null, latencies: [], offsetMs: null, pings: [],
  points: {}, frameSize: [640, 480], status: null, jog: null, reqId: 0, picked: [],
  reconnectMs: RECONNECT_MIN_MS, pendingHead: null, deadman: 0, lastReply: null,
  ghost: null, ghostDrawn: false, viewAck: null, sigma: null, run: null, timing: [],
  offsetErrMs: null, burst: 0, marks: {},  // first open, hello, frame_in, frame: ms from navigation
};
window.orbitar = state;  // for the browser tests and the curious

// ---- connection --------------------------------------------------------------------------

function tokenFromPage() {
  const hash = new URLSearchParams(location.hash.slice(1));
  return hash.get("token") || sessionStorage.getItem("orbitar-token") || "";
}

function connect() {
  state.token = tokenFromPage();
  if (!state.token) { showLogin("This station needs a token."); return; }
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const ws = new WebSocket(`${scheme}://${location.host}/ws`);
  ws.binaryType = "arraybuffer";
  state.ws = ws;
  ws.onopen = () => { mark("open"); ws.send(JSON.stringify({ type: "hello", token: state.token })); };
  ws.onmessage = (ev) => (typeof ev.data === "string" ? onJson(JSON.parse(ev.data)) : onFrame(ev.data));
  ws.onclose = (ev) => onClosed(ev);
}

function onClosed(ev) {
  state.connected = false;
  endJog("connection lost");
  setConn(false, ev.code === 4401 ? "token refused" : "disconnected — reconnecting…");
  if (ev.code === 4401) { state.refused = true; showLogin("The daemon refused this token."); return; }
  setTimeout(connect, state.reconnectMs);
  state.reconnectMs = Math.min(state.reconnectMs * 2, RECONNECT_MAX_MS);
}

// The first time this page got somewhere, on the clock that starts at navigation.
function mark(name) { if (state.marks[name] === undefined) state.marks[name] = performance.now(); }

function send(msg) {
  if (state.ws && state.ws.readyState === WebSocket.OPEN) { state.ws.send(JSON.stringify(msg)); return true; }
  return false;
}

function op(name, args = {}) {
  state.reqId += 1;
  return send({ type: "op", id: state.reqId, op: name, args });
}

function onJson(msg) {
  if (msg.type === "hello") return onHello(msg);
  if (msg.type === "status") return onStatus(msg);
  if (msg.type === "pong") return onPong(msg);
  if (msg.type === "reply") {
    state.lastReply = msg;
    if (!msg.ok) toast(`${msg.op}: ${msg.code} — ${msg.message || ""}`);
    return undefined;
  }
  if (msg.type === "view") { state.viewAck = msg; return undefined; }
  if (msg.type === "info") return onInfo(msg);
  if (msg.type === "deadman") { state.deadman += 1; toast(`stopped by the dead-man rule: ${msg.why}`); }
  if (msg.type === "error") toast(`${msg.code}`);
  return undefined;
}

function onHello(msg) {
  mark("hello");
  state.connected = true; state.refused = false; state.role = msg.role; state.info = msg;
  state.reconnectMs = RECONNECT_MIN_MS;
  sessionStorage.setItem("orbitar-token", state.token);
  $("login").hidden = true;
  document.body.classList.toggle("viewer", msg.role !== "operator");
  $("role").textContent = msg.role === "operator" ? "operator" : "viewer (no motion)";
  setConn(true, "connected");
  setupHead(msg.head_deg); drawPlan(msg.track); showParts(msg.parts); setupRuns(msg.runs || []);
  if (state.ghost === null) state.ghost = Boolean(msg.ghost);
  $("ghost").checked = state.ghost; sendView();
  state.burst = PING_BURST; ping();
}

// The rig file changed (a calibration was written): new intrinsics, limits and track plan.
function onInfo(msg) {
  state.info = { ...state.info, ...msg, role: state.info.role };
  setupHead(msg.head_deg); drawPlan(msg.track);
}

function setConn(ok, text) {
  const el = $("conn"); el.textContent = text; el.className = ok ? "ok" : "bad";
}

function ping() { send({ type: "ping", t: performance.now() }); }

// As NTP: the daemon stamps the ping's receipt and the pong's sending, so the time the pong
// waited in the daemon (behind a frame being written) is not taken for network delay. The
// fastest round trip of the last ten gives the offset, within half that round trip.
function onPong(msg) {
  const now = performance.now(); const held = (msg.sent_ms ?? msg.host_ms) - msg.host_ms;
  const rtt = now - msg.t - held;
  state.pings.push({ rtt, held, offset: (msg.host_ms + held / 2) - (msg.t + (now - msg.t) / 2) });
  if (state.pings.length > 10) state.pings.shift();
  const best = state.pings.reduce((a, b) => (b.rtt < a.rtt ? b : a));  // fastest wins
  state.offsetMs = best.offset; state.offsetErrMs = best.rtt / 2;
  if (state.burst > 1) { state.burst -= 1; ping(); } else state.burst = 0;
}

// ---- frames ------------------------------------------------------------------------------

// A frame is acknowledged once drawn: the daemon sends the next only then, so at most one frame
// is in flight (benchmarks/bench_station.py measured acknowledging on arrival instead: on a
// loaded 2-core machine the extra frames received and decoded cost more than the overlap saved).
// createImageBitmap decodes off the main thread.
async function onFrame(buffer) {
  const receivedMs = performance.now();
  mark("frame_in");
  const view = new DataView(buffer);
  const headLen = view.getUint32(0);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, headLen)));
  const blob = new Blob([new Uint8Array(buffer, 4 + headLen)], { type: "image/jpeg" });
  let latency = null;
  try {
    const bitmap = await createImageBitmap(blob);
    const decodedMs = performance.now();
    const canvas = $("view");
    if (canvas.width !== bitmap.width || canvas.height !== bitmap.height) {
      canvas.width = bitmap.width; canvas.height = bitmap.height;
    }
    // The decoded bitmap becomes the canvas' image as it is: no copy drawn on the main thread,
    // which also reads the pongs (a 2D drawImage per frame kept their round trip at 40-75 ms).
    canvas.getContext("bitmaprenderer").transferFromImageBitmap(bitmap);
    latency = drawn(header, receivedMs, decodedMs);
    mark("frame");
  } catch (err) {
    toast(`frame ${header.index} not shown: ${err}`);
  } finally {
    send({ type: "ack", index: header.index, latency_ms: latency });
  }
}

function drawn(header, receivedMs, decodedMs) {
  const now = performance.now();
  const latency = state.offsetMs === null ? null : now + state.offsetMs - header.exposure_ms;
  if (latency !== null) {  // where the time went: daemon, network, decode, draw
    const t = {
      daemon: header.age_at_send_ms, transit: receivedMs + state.offsetMs - header.sent_ms,
      decode: decodedMs - receivedMs, draw: now - decodedMs, total: latency,
    };
    state.timing.push(t); if (state.timing.length > TIMING_KEEP) state.timing.shift();
  }
  state.frames += 1; state.points = header.points || {}; state.frameSize = [header.width, header.height];
  state.ghostDrawn = Boolean(header.ghost);
  state.lastLatencyMs = latency;
  if (latency !== null) { state.latencies.push(latency); if (state.latencies.length > 300) state.latencies.shift(); }
  state.fpsTimes.push(now);
  while (state.fpsTimes.length && state.fpsTimes[0] < now - 2000) state.fpsTimes.shift();
  const homed = !state.status || (state.status.link || {}).homed !== false;
  let note = header.registered ? "" : "no pose for this frame: overlay withheld";
  if (header.registered && !homed) note = "not homed: the overlay assumes the trolley at home until Home is run";
  $("ghost-note").textContent = state.ghost && header.registered && !header.ghost ? "(none yet: no drift correction running)" : "";
  setText($("viewnote"), note);
  $("viewnote").hidden = !note;
  return latency;
}

// Writing only what changed keeps the page from re-laying out for nothing on every frame.
function setText(el, text) { if (el.textContent !== text) el.textContent = text; }

function pageFps() {
  const t = state.fpsTimes;
  return t.length < 2 ? 0 : ((t.length - 1) * 1000) / (t[t.length - 1] - t[0]);
}

// ---- motion: press-and-hold jog with a dead-man --------------------------------------------

function startJog(button) {
  if (state.role !== "operator" || state.jog) return;
  const fast = button.dataset.fast ? 3 : 1;
  const v = Number(button.dataset.dir) * Number($("speed").value) * fast;
  op("jog", { velocity_mm_s: v });
  send({ type: "hold" });
  state.jog = { button, timer: setInterval(() => send({ type: "hold" }), HOLD_PERIOD_MS) };
  button.classList.add("held");
}

function endJog(why) {
  if (!state.jog) return;
  clearInterval(state.jog.timer);
  state.jog.button.classList.remove("held");
  state.jog = null;
  op("jog", { velocity_mm_s: 0 });
  if (why) toast(`jog ended: ${why}`);
}

for (const button of document.querySelectorAll(".jogbtn")) {
  button.addEventListener("pointerdown", (ev) => {
    ev.preventDefault(); button.setPointerCapture(ev.pointerId); startJog(button);
  });
  for (const type of ["pointerup", "pointercancel", "lostpointercapture"]) {
    button.addEventListener(type, () => endJog());
  }
  button.addEventListener("contextmenu", (ev) => ev.preventDefault());
}
window.addEventListener("blur", () => endJog("the page lost focus"));
document.addEventListener("visibilitychange", () => { if (document.hidden) endJog("the page was hidden"); });
window.addEventListener("pagehide", () => endJog());

$("estop").addEventListener("pointerdown", (ev) => { ev.preventDefault(); endJog(); op("estop"); });
$("stop").addEventListener("pointerdown", (ev) => { ev.preventDefault(); endJog(); op("stop"); });
$("home").addEventListener("click", () => op("home"));
$("clear").addEventListener("click", () => op("clear"));
$("speed").addEventListener("input", () => { $("speed-out").textContent = `${$("speed").value} mm/s`; });

// ---- head: sliders and drag on the view --------------------------------------------------

function setupHead(limits) {
  for (const axis of ["pan", "tilt"]) {
    const el = $(axis); el.min = limits[axis][0]; el.max = limits[axis][1];
  }
}

function sendHead(panDeg, tiltDeg) {
  const clamp = (v, [lo, hi]) => Math.min(hi, Math.max(lo, v));
  const lim = state.info.head_deg;
  const pan = clamp(panDeg, lim.pan); const tilt = clamp(tiltDeg, lim.tilt);
  $("pan").value = pan; $("tilt").value = tilt; showHead(pan, tilt);
  op("head", { pan_rad: (pan * Math.PI) / 180, tilt_rad: (tilt * Math.PI) / 180 });
}

function showHead(pan, tilt) {
  $("pan-out").textContent = `${Number(pan).toFixed(1)}°`; $("tilt-out").textContent = `${Number(tilt).toFixed(1)}°`;
}

for (const axis of ["pan", "tilt"]) {
  $(axis).addEventListener("input", () => showHead($("pan").value, $("tilt").value));
  $(axis).addEventListener("change", () => sendHead(Number($("pan").value), Number($("tilt").value)));
}

const canvas = $("view");
let drag = null;
canvas.addEventListener("pointerdown", (ev) => {
  canvas.setPointerCapture(ev.pointerId);
  drag = { x: ev.clientX, y: ev.clientY, pan: Number($("pan").value), tilt: Number($("tilt").value), moved: false };
});
// The head turns by the angle the dragged pixels subtend through the calibrated intrinsics,
// so the scene follows the finger whatever the lens and the view's size on screen.
function dragDeg(d, ev) {
  const rect = canvas.getBoundingClientRect(); const cam = state.info.camera;
  const sx = cam.width / rect.width; const sy = cam.height / rect.height;  // camera pixels
  const u = (x) => (x - rect.left) * sx; const v = (y) => (y - rect.top) * sy;
  const angle = (a, b, c, f) => ((Math.atan((b - c) / f) - Math.atan((a - c) / f)) * 180) / Math.PI;
  return [angle(u(d.x), u(ev.clientX), cam.u0, cam.fx), angle(v(d.y), v(ev.clientY), cam.v0, cam.fy)];
}

canvas.addEventListener("pointermove", (ev) => {
  if (!drag) return;
  const dx = ev.clientX - drag.x; const dy = ev.clientY - drag.y;
  if (Math.hypot(dx, dy) > TAP_SLOP_PX) drag.moved = true;
  if (drag.moved && state.role === "operator") {
    const [pan, tilt] = dragDeg(drag, ev);
    $("pan").value = drag.pan - pan; $("tilt").value = drag.tilt + tilt;
    drag.target = [drag.pan - pan, drag.tilt + tilt];
    showHead(drag.target[0], drag.target[1]);
  }
});
canvas.addEventListener("pointerup", (ev) => {
  if (!drag) return;
  const d = drag; drag = null;
  if (d.moved && state.role === "operator" && d.target) sendHead(d.target[0], d.target[1]);
  else if (!d.moved) tapView(ev);
});
canvas.addEventListener("pointercancel", () => { drag = null; });

function tapView(ev) {
  const rect = canvas.getBoundingClientRect();
  const u = ((ev.clientX - rect.left) * state.frameSize[0]) / rect.width;
  const v = ((ev.clientY - rect.top) * state.frameSize[1]) / rect.height;
  let best = null;
  for (const [name, [pu, pv]] of Object.entries(state.points)) {
    const d = Math.hypot(pu - u, pv - v);
    if (d < 40 && (!best || d < best.d)) best = { name, d };
  }
  if (best) pickPoint(best.name);
}

// ---- the ghost: this page's choice, drawn by the daemon into this page's frames ----------

function sendView() { if (state.ghost !== null) send({ type: "view", ghost: state.ghost }); }

$("ghost").addEventListener("change", () => { state.ghost = $("ghost").checked; sendView(); });

// ---- the track plan ------------------------------------------------------------------------

const SVG = "http://www.w3.org/2000/svg";
let planBox = null;

function svgEl(tag, attrs) {
  const el = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) el.setAttribute(k, v);
  return el;
}

function drawPlan(track) {
  const svg = $("plan"); svg.replaceChildren();
  const xs = track.plan_xy_mm.map((p) => p[0]); const ys = track.plan_xy_mm.map((p) => -p[1]);
  const pad = 300;
  planBox = { x: Math.min(...xs) - pad, y: Math.min(...ys) - pad };
  planBox.w = Math.max(...xs) + pad - planBox.x; planBox.h = Math.max(...ys) + pad - planBox.y;
  svg.setAttribute("viewBox", `${planBox.x} ${planBox.y} ${planBox.w} ${planBox.h}`);
  const pts = track.plan_xy_mm.map((p) => `${p[0]},${-p[1]}`).join(" ");
  svg.append(svgEl(track.closed ? "polygon" : "polyline", { points: pts, class: "rail" }));
  for (const m of track.marks) svg.append(svgEl("circle", { cx: m.xy[0], cy: -m.xy[1], r: 60, class: "mark" }));
  const home = nearestPlanPoint(track.home_s_mm);
  if (home) svg.append(svgEl("rect", { x: home[0] - 70, y: -home[1] - 70, width: 140, height: 140, class: "home" }));
  svg.append(svgEl("circle", { id: "trolley", cx: 0, cy: 0, r: 110, class: "trolley", visibility: "hidden" }));
  svg.append(svgEl("circle", { id: "target", cx: 0, cy: 0, r: 160, class: "target", visibility: "hidden" }));
}

function nearestPlanPoint(s) {
  const t = state.info.track; let best = 0;
  for (let i = 0; i < t.plan_s_mm.length; i++) if (Math.abs(t.plan_s_mm[i] - s) < Math.abs(t.plan_s_mm[best] - s)) best = i;
  return t.plan_xy_mm[best];
}

function planPositionAt(s) {
  const t = state.info.track; const ss = t.plan_s_mm; const xy = t.plan_xy_mm;
  const len = t.length_mm; let q = t.closed ? ((s % len) + len) % len : Math.min(Math.max(s, 0), len);
  for (let i = 1; i < ss.length; i++) {
    if (q <= ss[i]) {
      const f = (q - ss[i - 1]) / (ss[i] - ss[i - 1] || 1);
      return [xy[i - 1][0] + f * (xy[i][0] - xy[i - 1][0]), xy[i - 1][1] + f * (xy[i][1] - xy[i - 1][1])];
    }
  }
  return xy[xy.length - 1];
}

$("plan").addEventListener("pointerup", (ev) => {
  if (state.role !== "operator" || !state.info) return;
  const svg = $("plan"); const pt = svg.createSVGPoint(); pt.x = ev.clientX; pt.y = ev.clientY;
  const p = pt.matrixTransform(svg.getScreenCTM().inverse());
  const t = state.info.track; let best = 0; let bestD = Infinity;
  t.plan_xy_mm.forEach((q, i) => { const d = Math.hypot(q[0] - p.x, -q[1] - p.y); if (d < bestD) { bestD = d; best = i; } });
  if (bestD > 600) return;
  const s = t.plan_s_mm[best];
  const target = $("target"); target.setAttribute("cx", t.plan_xy_mm[best][0]); target.setAttribute("cy", -t.plan_xy_mm[best][1]);
  target.setAttribute("visibility", "visible");
  $("plan-note").textContent = `moving to s = ${s.toFixed(0)} mm`;
  op("move_track", { track_s_mm: s, speed_mm_s: Number($("speed").value) });
});

// ---- status --------------------------------------------------------------------------------

// The hall's rigs from the bus (null: this daemon is not on a bus, the panel stays hidden).
function showHall(rigs) {
  $("hall-panel").hidden = !rigs;
  if (!rigs) return;
  const table = $("hall"); table.replaceChildren();
  const head = document.createElement("tr");
  for (const h of ["rig", "", "state", "position", "link", "age"]) {
    const th = document.createElement("th"); th.textContent = h; head.append(th);
  }
  table.append(head);
  for (const r of rigs) {
    const cells = [
      [r.self ? `${r.rig} (this rig)` : r.rig, ""],
      [r.alive ? "alive" : "gone", r.alive ? "ok" : "bad"],
      [r.state ?? "—", r.state === "FAULT" || r.state === "ESTOP" ? "bad" : ""],
      [fmt(r.position_mm, 1, " mm"), ""],
      [r.link_up === true ? "up" : r.link_up === false ? "down" : "—", r.link_up === false ? "bad" : ""],
      [fmt(r.age_s, 1, " s"), ""],
    ];
    const tr = document.createElement("tr"); tr.dataset.rig = r.rig;
    for (const [text, cls] of cells) {
      const td = document.createElement("td"); td.textContent = text; if (cls) td.className = cls; tr.append(td);
    }
    table.append(tr);
  }
}

const fmt = (v, digits = 1, unit = "") => (v === null || v === undefined || Number.isNaN(v) ? "—" : `${Number(v).toFixed(digits)}${unit}`);
const deg = (rad) => (rad === null || rad === undefined ? null : (rad * 180) / Math.PI);

function onStatus(msg) {
  state.status = msg;
  const st = msg.status || {}; const ctrl = st.controller || {}; const link = msg.link || {};
  const svc = st.service || {}; const frames = msg.frames || {}; const stn = msg.station || {};
  // The budget is evaluated in the daemon's background at a pose: its age is that pose's age.
  const sigmaPx = typeof svc.overlay_sigma_px === "number" ? svc.overlay_sigma_px : null;
  const sigmaAge = svc.overlay_sigma_age_s;
  const poseAt = typeof sigmaAge === "number" ? msg.host_ms - sigmaAge * 1000 : null;
  state.sigma = { px: sigmaPx, at_host_ms: poseAt };
  const pose = st.pose; const head = ctrl.head_rad || [null, null];
  const ageMs = pose ? msg.host_ms - pose.t_ns / 1e6 : null;
  const src = frames.source || {};
  const rows = [
    ["link", st.link_up ? "up" : `down ${svc.link_error || ""}`, st.link_up ? "ok" : "bad"],
    ["RTT", fmt(link.rtt_ms, 1, " ms")],
    ["retransmits / lost", `${link.retransmits ?? "—"} / ${link.rx_lost ?? "—"}`],
    ["drops (bad frames)", `${link.drops ?? "—"}`],
    ["clock sync σ", fmt(link.clock_sigma_us, 1, " µs")],
    ["state", ctrl.state || "—", ctrl.state === "FAULT" || ctrl.state === "ESTOP" ? "bad" : ""],
    ["faults", faultText(ctrl), ctrl.faults ? "bad" : "ok"],
    ["position", fmt(ctrl.position_mm, 1, " mm")],
    ["homed", link.homed ? "yes" : "no — press Home to reference the track", link.homed ? "ok" : "bad"],
    ["track s (corrected)", fmt(link.track_s_mm, 1, " mm")],
    ["head pan / tilt", `${fmt(deg(head[0]), 2, "°")} / ${fmt(deg(head[1]), 2, "°")}`],
    ["chain scale", link.chain_scale === undefined ? "— (no references)" : fmt(link.chain_scale, 5)],
    ["references used / rejected", link.references_used === undefined ? "—" : `${link.references_used} / ${link.references_rejected}`],
    ["tooth skips found", link.skips_detected ?? "—"],
    ["position σ", fmt(link.position_sigma_mm, 2, " mm")],
    ["pose age", fmt(ageMs, 0, " ms")],
    ["overlay σ (predicted)", sigmaText(), state.sigma && state.sigma.px !== null ? "" : "bad"],
    ["camera", `${src.kind || "none"} ${src.state || ""} ${src.detail || ""}`, src.state && src.state !== "running" ? "bad" : ""],
    ["frame loop", `${fmt(svc.fps, 1, " fps")}, dropped ${frames.dropped ?? 0}`],
    ["view", `${fmt(pageFps(), 1, " fps")}, ${latencyText()} latency`],
    ["encoder", `${fmt(stn.encode_fps, 1, " fps")}, ${fmt(stn.encode_cpu_ms, 1, " ms")}/frame, dropped ${stn.encode_dropped ?? 0}`],
    ["viewers", `${stn.viewers ?? 0}`],
  ];
  const table = $("status");
  if (table.rows.length !== rows.length) {
    table.replaceChildren();
    for (let i = 0; i < rows.length; i++) table.append(document.createElement("tr"));
    for (const tr of table.rows) tr.append(document.createElement("th"), document.createElement("td"));
  }
  rows.forEach(([k, v, cls], i) => {  // in place: a status push re-lays out only what changed
    const [th, td] = table.rows[i].cells;
    setText(th, k); setText(td, v); if (td.className !== (cls || "")) td.className = cls || "";
  });
  showFigures();
  const latched = ctrl.state === "ESTOP" || ctrl.state === "FAULT";
  const faults = (ctrl.fault_names || []).join(", ");
  $("motion-state").textContent = latched ? `${ctrl.state} LATCHED (${faults}): Clear releases` : ctrl.state || "";
  $("motion-state").classList.toggle("latched", latched);
  showHall(msg.hall);
  showRun(msg.commissioning);
  showTrolley(link.track_s_mm ?? (ctrl.position_mm ?? null));
  if (!drag && head[0] !== null && document.activeElement !== $("pan") && document.activeElement !== $("tilt")) {
    $("pan").value = deg(head[0]); $("tilt").value = deg(head[1]); showHead(deg(head[0]), deg(head[1]));
  }
}

// The predicted overlay σ and its age on the daemon's clock (it keeps counting if status stops).
function sigmaAgeS() {
  const sg = state.sigma;
  if (!sg || sg.at_host_ms === null || state.offsetMs === null) return null;
  return (performance.now() + state.offsetMs - sg.at_host_ms) / 1000;
}

function sigmaText() {
  const sg = state.sigma;
  if (!sg || sg.px === null) return "unknown (no error budget for this pose)";
  const age = sigmaAgeS();
  return `${sg.px.toFixed(1)} px, ${age === null ? "age unknown" : `${age.toFixed(1)} s old`}`;
}

function showFigures() {
  const ctrl = ((state.status || {}).status || {}).controller || {};
  const sg = state.sigma; const age = sigmaAgeS();
  const sigma = !sg || sg.px === null ? "σ unknown" : `σ ${sg.px.toFixed(1)} px (${age === null ? "?" : age.toFixed(1)} s)`;
  setText($("figures"), `${fmt(pageFps(), 0)} fps · ${latencyText()} · ${fmt(ctrl.position_mm, 0, " mm")} · ${sigma}`);
}

// The page's latency with what the clock offset allows of it.
function latencyText() {
  if (state.lastLatencyMs === null) return "— ms";
  return `${state.lastLatencyMs.toFixed(0)} ± ${Math.max(1, Math.ceil(state.offsetErrMs ?? 0))} ms`;
}

function faultText(ctrl) {
  const names = ctrl.fault_names || [];
  if (names.length) return names.join(", ");
  return ctrl.faults ? `0x${Number(ctrl.faults).toString(16).padStart(4, "0")} (unnamed bits)` : "none";
}

function showTrolley(s) {
  const el = $("trolley"); if (!el || s === null || !state.info) return;
  const [x, y] = planPositionAt(s);
  el.setAttribute("cx", x); el.setAttribute("cy", -y); el.setAttribute("visibility", "visible");
}

// ---- the workpiece: parts, feature points, measuring ----------------------------------------

function showParts(parts) {
  $("parts-title").textContent = parts.title || "Workpiece";
  const list = $("parts"); list.replaceChildren();
  for (const part of parts.parts) {
    const b = document.createElement("button"); b.type = "button"; b.textContent = part.name;
    b.addEventListener("click", () => showPart(part)); list.append(b);
  }
  const pts = $("points"); pts.replaceChildren();
  for (const p of parts.feature_points) {
    const b = document.createElement("button"); b.type = "button"; b.textContent = p.name; b.dataset.point = p.name;
    b.title = p.notes; b.addEventListener("click", () => pickPoint(p.name)); pts.append(b);
  }
  if (!parts.parts.length && !parts.feature_points.length) list.textContent = "No parts sidecar beside the model.";
}

function showPart(part) {
  const panel = $("part-panel"); panel.hidden = false; panel.replaceChildren();
  const h = document.createElement("strong"); h.textContent = part.name;
  const notes = document.createElement("p"); notes.textContent = part.notes || "";
  const pts = document.createElement("p");
  pts.textContent = part.points.length ? `feature points: ${part.points.join(", ")}` : "no feature points";
  panel.append(h, notes, pts);
}

function pickPoint(name) {
  const all = state.info.parts.feature_points; const p = all.find((q) => q.name === name);
  if (!p) return;
  state.picked = [...state.picked.filter((n) => n !== name), name].slice(-2);
  for (const b of $("points").children) b.classList.toggle("picked", state.picked.includes(b.dataset.point));
  const part = state.info.parts.parts.find((q) => q.points.includes(name));
  if (part) showPart(part);
  if (state.picked.length === 2) {
    const [a, b] = state.picked.map((n) => all.find((q) => q.name === n).position_mm);
    const d = Math.hypot(a[0] - b[0], a[1] - b[1], a[2] - b[2]);
    $("measure").textContent = `${state.picked[0]} → ${state.picked[1]}: ${d.toFixed(1)} mm`;
    state.measuredMm = d;
  } else {
    $("measure").textContent = `${name}: ${p.notes || ""} — pick one more point`;
  }
}

// ---- commissioning: runs started here through the same ops as `orbitar calibrate` ----------

// Fields of the runs this page knows (docs/COMMISSIONING.md); an empty field is left out, so the
// daemon's default applies. A run the daemon offers that is not listed gets a JSON arguments box.
const BOARD_FIELDS = [
  ["board.squares_x", "int", "board squares across"], ["board.squares_y", "int", "board squares down"],
  ["board.square_mm", "number", "square edge, mm"], ["board.marker_mm", "number", "marker edge, mm"],
];
const POSE_FIELDS = [
  ["board_pose", "json", "board pose (surveyed), 4×4 JSON, mm"],
  ["board_sigma_mm", "number", "its survey σ, mm"], ["board_sigma_rad", "number", "its survey σ, rad"],
];
const SPEED = ["speed_mm_s", "number", "trolley speed, mm/s"];
const WRITE = ["write", "bool", "write the rig file if it passes", true];
const STATIONS = ["stations_mm", "list", "stations s, mm (empty: here)"];
const RUN_FORMS = {
  calibrate_intrinsics: { title: "Camera intrinsics (board)", fields: [
    ["board_centre_mm", "vec3", "board centre X Y Z, mm (tape)"], STATIONS, ...BOARD_FIELDS,
    ["min_views", "int", "views needed"], ["max_rms_px", "number", "pass if RMS ≤, px"],
    ["full_distortion", "bool", "also p1, p2, k3", false], SPEED, WRITE] },
  calibrate_head: { title: "Head (M_cr) and track placement", fields: [...POSE_FIELDS, STATIONS, ...BOARD_FIELDS, SPEED, WRITE] },
  calibrate_check: { title: "Acceptance check", fields: [...POSE_FIELDS, STATIONS, ...BOARD_FIELDS,
    ["max_rms_px", "number", "pass if RMS ≤, px"], SPEED] },
  calibrate_latency: { title: "Frame latency", fields: [...POSE_FIELDS.slice(0, 1),
    ["station_mm", "number", "station facing the board, mm"], ["span_mm", "number", "pass length, mm"],
    ["passes", "int", "passes"], ...BOARD_FIELDS, SPEED, WRITE] },
  survey_workpiece: { title: "Workpiece survey (rangefinder or camera targets)", fields: [
    ["method", "choice", "method", ["rangefinder", "camera"]],
    ["model_points_mm", "json", "model points [[x, y, z], …] (the sidecar's)", sidecarPoints],
    ["aims", "json", "rangefinder: aims [[s_mm, pan_rad, tilt_rad], …]"],
    ["samples", "int", "rangefinder: readings per point"],
    ["stations_mm", "list", "camera: stations s, mm (empty: here)"], WRITE] },
  survey_marks: { title: "Reference marks (rangefinder)", fields: [
    ["marks", "list", "marks to survey, indices (empty: all)"], ["samples", "int", "readings per mark"],
    ["aim_rad", "json", "aim [pan_rad, tilt_rad] (empty: planned)"],
    ["cross_speed_mm_s", "number", "speed across a mark, mm/s"], ["max_sigma_mm", "number", "pass if σ ≤, mm"], WRITE] },
  calibrate_rangefinder: { title: "Rangefinder mount", fields: [
    STATIONS, ["pans", "int", "pans per station"], ["aims", "json", "or aims [[s_mm, pan_rad, tilt_rad], …]"],
    ["samples", "int", "readings per pose"], ["max_rms_mm", "number", "pass if RMS ≤, mm"], SPEED, WRITE] },
  survey_track: { title: "Track: first corner and arc radius (rangefinder)", fields: [
    ["stations_mm", "list", "stations s, mm (empty: before and on the first arc)"],
    ["pans", "int", "pans per station"], ["samples", "int", "readings per pose"],
    ["max_corner_sigma_mm", "number", "pass if corner σ ≤, mm"],
    ["max_radius_sigma_mm", "number", "pass if radius σ ≤, mm"],
    ["max_rms_mm", "number", "pass if RMS ≤, mm"], SPEED, WRITE] },
  survey_home: { title: "Home survey (rangefinder)", fields: [
    ["pan_rad", "deg", "pan at an end wall, °"], ["tilt_rad", "deg", "tilt, °"], ["samples", "int", "readings"], WRITE] },
};
const COVERAGE_KEYS = ["x", "y", "size", "skew"];

// The parts sidecar's feature points (model frame), where a survey's targets are stuck.
function sidecarPoints() {
  const pts = ((state.info && state.info.parts) || {}).feature_points || [];
  return pts.length ? JSON.stringify(pts.map((p) => p.position_mm)) : "";
}

function setupRuns(runs) {
  const select = $("run-op"); const keep = select.value; select.replaceChildren();
  $("comm-panel").hidden = !runs.length;
  for (const name of runs) {
    const o = document.createElement("option"); o.value = name;
    o.textContent = (RUN_FORMS[name] || {}).title || name; select.append(o);
  }
  if (runs.includes(keep)) select.value = keep;
  buildRunForm();
  $("run-who").textContent = state.role === "operator" ? "" : "(viewer: follow only)";
}

function buildRunForm() {
  const name = $("run-op").value; const form = $("run-form");
  if (form.dataset.op === name) return;
  form.replaceChildren(); form.dataset.op = name;
  const fields = (RUN_FORMS[name] || { fields: [["", "args", "arguments, JSON object"]] }).fields;
  for (const [key, kind, label, dflt] of fields) {
    const row = document.createElement("label"); const span = document.createElement("span");
    span.textContent = label;
    const tag = kind === "json" || kind === "args" ? "textarea" : kind === "choice" ? "select" : "input";
    const input = document.createElement(tag);
    input.dataset.key = key; input.dataset.kind = kind;
    if (kind === "choice") {
      for (const value of dflt) { const o = document.createElement("option"); o.value = o.textContent = value; input.append(o); }
    } else if (kind === "bool") { input.type = "checkbox"; input.checked = Boolean(dflt); } else if (tag === "input") { input.type = "text"; }
    if (typeof dflt === "function") input.value = dflt();
    if (kind === "vec3") input.placeholder = "x y z";
    row.append(span, input); form.append(row);
  }
}

// The form as the op's arguments; a malformed field throws with its label.
function runArgs() {
  const args = {};
  for (const input of $("run-form").querySelectorAll("[data-key]")) {
    const { key, kind } = input.dataset; const text = input.value.trim();
    const label = input.previousSibling.textContent;
    let value;
    if (kind === "bool") value = input.checked;
    else if (!text) continue;
    else if (kind === "args") { Object.assign(args, JSON.parse(text)); continue; }
    else if (kind === "choice") value = text;
    else if (kind === "json") value = JSON.parse(text);
    else if (kind === "vec3" || kind === "list") value = text.split(/[\s,;]+/).filter(Boolean).map(Number);
    else if (kind === "deg") value = (Number(text) * Math.PI) / 180;
    else value = Number(text);
    if ((kind === "number" || kind === "int" || kind === "deg") && !Number.isFinite(value)) throw new Error(`${label}: not a number`);
    if (kind === "int" && !Number.isInteger(value)) throw new Error(`${label}: not a whole number`);
    if ((kind === "vec3" || kind === "list") && value.some((x) => !Number.isFinite(x))) throw new Error(`${label}: numbers only`);
    const [outer, inner] = key.split(".");
    if (inner) { args[outer] = args[outer] || {}; args[outer][inner] = value; } else args[outer] = value;
  }
  return args;
}

$("run-op").addEventListener("change", buildRunForm);
$("run-start").addEventListener("click", () => {
  let args;
  try { args = runArgs(); } catch (err) { toast(`run not started: ${err.message}`); return; }
  op($("run-op").value, args);
});
$("run-cancel").addEventListener("click", () => op("commissioning_cancel"));

function bar(label, value, cls, need, text) {
  const row = document.createElement("div"); row.className = "bar";
  const name = document.createElement("span"); name.textContent = label;
  const track = document.createElement("div"); track.className = "track";
  const fill = document.createElement("div"); fill.className = `fill ${cls}`;
  fill.style.width = `${Math.max(0, Math.min(1, value)) * 100}%`; track.append(fill);
  if (need !== null) {
    const mark = document.createElement("div"); mark.className = "need"; mark.style.left = `${need * 100}%`; track.append(mark);
  }
  const out = document.createElement("span"); out.textContent = text;
  row.append(name, track, out);
  return row;
}

// Per-view errors from a finished run: RMS per kept view (intrinsics, head, check), the views
// dropped as outliers (their RMS is not reported), or the survey's residual per point.
function perViewRows(result) {
  const rows = [];
  if (Array.isArray(result.per_view_rms_px)) {
    const dropped = new Set(result.rejected_views || []);
    const kept = (result.views || {}).ok ?? result.per_view_rms_px.length + dropped.size;
    const errors = [...result.per_view_rms_px];
    for (let j = 0; j < Math.max(kept, errors.length); j++) {
      if (dropped.has(j)) rows.push({ label: `view ${j + 1}`, value: null, outlier: true, unit: "px" });
      else rows.push({ label: `view ${j + 1}`, value: errors.length ? errors.shift() : null, outlier: false, unit: "px" });
    }
  } else if (Array.isArray(result.residuals_mm)) {
    result.residuals_mm.forEach((r, i) => {
      const v = Array.isArray(r) ? Math.hypot(...r) : r;
      rows.push({ label: `P${i + 1}`, value: v, outlier: false, unit: "mm" });
    });
  }
  return rows;
}

// Per-view errors while a run captures (its progress' view_errors): a board view's corners about
// their PnP pose with the rig file's intrinsics, or a surveyed point's reading spread.
function liveViewRows(entries) {
  return entries.map((e) => {
    const mm = e.spread_mm !== undefined;
    const value = mm ? e.spread_mm : e.rms_px;
    return { label: e.label, value: value ?? null, outlier: false, unit: mm ? "mm" : "px", note: e.status };
  });
}

function showRun(run) {
  state.run = run || null;
  const running = Boolean(run && run.state === "running");
  $("run-start").disabled = running; $("run-cancel").disabled = !running;
  if (!run || run.state === "none") { $("run-state").textContent = "No run yet."; return; }
  if (run.state === "unavailable") {
    $("run-state").textContent = `Commissioning unavailable: ${run.reason || ""}`;
    $("run-start").disabled = true; return;
  }
  const p = run.progress || {}; const title = (RUN_FORMS[`calibrate_${run.kind}`] || RUN_FORMS[`survey_${run.kind}`] || {}).title || run.kind;
  const where = p.of ? `, view ${p.view} of ${p.of}${p.label ? ` (${p.label})` : ""}` : "";
  const counts = p.accepted === undefined ? "" : ` — ${p.accepted} kept, ${p.blurred ?? 0} blurred, ${p.not_found ?? 0} without the board`;
  const what = run.state === "running" ? `${p.phase || "running"}${where}${counts}` : run.state;
  $("run-state").textContent = `Run ${run.id} · ${title}: ${what} · ${fmt(run.elapsed_s, 0, " s")}`;
  const result = run.result || {};
  const cov = p.coverage || result.coverage;
  const bars = $("run-coverage"); bars.replaceChildren();
  if (cov) {
    const need = (state.info && state.info.coverage_min) || {};
    for (const k of COVERAGE_KEYS) {
      const v = Number(cov[k] ?? 0); const n = need[k] ?? null;
      bars.append(bar(k.toUpperCase(), v, n !== null && v >= n ? "ok" : "", n, `${Math.round(v * 100)} %`));
    }
  }
  const verdict = $("run-verdict"); const reasons = $("run-reasons"); reasons.replaceChildren();
  const finished = run.state === "done" && typeof result.passed === "boolean";
  verdict.hidden = !finished && run.state === "running";
  if (finished) {
    verdict.textContent = result.passed ? "PASS" : "FAIL"; verdict.className = result.passed ? "pass" : "fail";
  } else if (run.state !== "running") {
    verdict.textContent = run.state === "cancelled" ? "CANCELLED: nothing written" : "ERROR: nothing written";
    verdict.className = "fail";
  }
  const why = finished ? result.reasons || [] : [run.reason || run.error].filter(Boolean);
  for (const text of why) { const li = document.createElement("li"); li.textContent = text; reasons.append(li); }
  if (finished && result.written) { const li = document.createElement("li"); li.textContent = `written to ${result.written}`; reasons.append(li); }
  const table = $("run-views"); table.replaceChildren();
  const live = !finished && Array.isArray(p.view_errors);
  const rows = finished ? perViewRows(result) : liveViewRows(live ? p.view_errors : []);
  if (rows.length) {
    const caption = document.createElement("caption");
    const mm = rows[0].unit === "mm";
    caption.textContent = finished ? (mm ? "residual per point" : "RMS per view, of the solution")
      : (mm ? "reading spread per point, as ranged" : "RMS per view about its PnP pose (rig file's lens), as captured");
    table.append(caption);
  }
  const top = Math.max(1e-9, ...rows.map((r) => r.value ?? 0));
  for (const r of rows) {
    const tr = document.createElement("tr"); tr.dataset.view = r.label;
    const name = document.createElement("td"); name.textContent = r.label;
    const cell = document.createElement("td"); cell.style.width = "100%";
    let text = r.outlier ? "outlier, dropped" : r.note || "not reported";
    if (r.value !== null) text = `${r.value.toFixed(3)} ${r.unit}`;
    cell.append(bar("", r.outlier ? 1 : (r.value ?? 0) / top, r.outlier ? "outlier" : "ok", null, text));
    if (r.outlier) { tr.classList.add("outlier"); name.className = "outlier"; }
    tr.append(name, cell); table.append(tr);
  }
  const link = $("run-report");
  link.hidden = !run.report_url;
  if (run.report_url) link.href = run.report_url;
}

// ---- little things -------------------------------------------------------------------------

let toastTimer = null;
function toast(text) {
  $("toast").textContent = text; clearTimeout(toastTimer);
  toastTimer = setTimeout(() => { $("toast").textContent = ""; }, 5000);
}

function showLogin(text) {
  $("login-msg").textContent = text; $("login").hidden = false;
}

$("login-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  sessionStorage.setItem("orbitar-token", $("token-input").value);
  history.replaceState(null, "", location.pathname);
  $("login").hidden = true; connect();
});

setInterval(ping, PING_PERIOD_MS);
setInterval(() => { if (state.status) showFigures(); }, 500);
connect();
