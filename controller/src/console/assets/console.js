// The Isowall operator console: live status over the /api/live WebSocket, the wall thumbnail
// fetched at THUMB_HZ from /api/snapshot.png?width=, charts drawn by hand on canvases, and the
// controls posting to /api/render, /api/camera and /api/time. No build step, no libraries.
// The page is cheap to keep open: it changes only the text and attributes that changed, redraws
// a chart only when a frame was added to it and the wall only when a thumbnail or a node's state
// is new, and asks for nothing while it is hidden (a tab in the background).
"use strict";

const THUMB_HZ = 1;
const LIVE_HZ = 2;
const AO_STEPS = [0, 1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024];

// A token given as #token=T in the address (kept for this tab only).
(function () {
  const m = location.hash.match(/token=([^&]+)/);
  if (m) {
    sessionStorage.setItem("isowall-token", decodeURIComponent(m[1]));
    history.replaceState(null, "", location.pathname);
  }
})();
const token = sessionStorage.getItem("isowall-token");
const authHeaders = token ? { Authorization: "Bearer " + token } : {};
// Never in a URL (it would end up in logs): a header, and for the WebSocket, which cannot send
// one, a subprotocol carrying the token's UTF-8 bytes in hex.
const hex = (text) => Array.from(new TextEncoder().encode(text), (b) => b.toString(16).padStart(2, "0")).join("");
const liveProtocols = token ? ["isowall", "isowall-token." + hex(token)] : ["isowall"];

const $ = (id) => document.getElementById(id);
let status = null;
// What the page measured, for the operator and for tests.
window.isowall = { thumbnails: 0, thumbBytes: 0, statusMessages: 0, lastFrame: null, latencyMs: null, latencies: [] };

// ---- live status ----
function connect() {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  const ws = new WebSocket(proto + "//" + location.host + "/api/live?hz=" + LIVE_HZ, liveProtocols);
  ws.onopen = () => { $("link").textContent = "live"; $("link").className = "good"; };
  ws.onmessage = (ev) => {
    window.isowall.statusMessages++;
    status = JSON.parse(ev.data);
    if (!document.hidden) show(status);
  };
  ws.onclose = () => {
    $("link").textContent = "reconnecting…";
    $("link").className = "bad";
    setTimeout(connect, 1000);
  };
}

function fmt(x, digits) {
  return x === null || x === undefined ? "–" : Number(x).toFixed(digits);
}

function since(s) {
  if (s < 60) return s.toFixed(0) + " s";
  if (s < 3600) return (s / 60).toFixed(0) + " min";
  return (s / 3600).toFixed(1) + " h";
}

// Changes an element's text, attribute or property only when it differs: the browser then lays
// out and paints only what changed.
function setText(el, t) { if (el.textContent !== t) el.textContent = t; }
function setProp(el, k, v) { if (el[k] !== v) el[k] = v; }
function setData(el, k, v) { if (el.dataset[k] !== v) el.dataset[k] = v; }

let charted = null; // the frame the charts show
let wallKey = null; // the wall's tiles and node states last drawn

function show(s) {
  setText($("wall-name"), s.wall.name + " (" + s.wall.width + "×" + s.wall.height + ", " + s.wall.mode + " space)");
  setText($("fps"), fmt(s.frame.fps, 1) + " fps");
  // A volume read through the nodes' brick caches: how much of the surface level 0 drew.
  const level0 = s.frame.level0_share === null ? "" : " · level 0 " + fmt(100 * s.frame.level0_share, 1) + "%";
  setText($("frame"), "frame " + s.frame.id + level0);
  setProp($("ro-badge"), "hidden", !s.console.read_only);
  setProp($("controls"), "hidden", s.console.read_only);
  showNodes(s);
  showControls(s);
  if (charted !== s.frame.id) {
    charted = s.frame.id;
    chart($("chart-frame"), s.frame.frame_ms, s.frame.frame_ms_p50, s.frame.frame_ms_p99, "#58a6ff");
    chart($("chart-skew"), s.frame.skew_ms, s.frame.skew_ms_p50, s.frame.skew_ms_p99, "#d29922");
    setText($("swap"), swapLine(s.frame));
  }
  const key = JSON.stringify([s.wall.width, s.wall.height, s.wall.tiles, s.nodes.map((n) => n.state)]);
  if (key !== wallKey) { wallKey = key; drawWall(); }
}

// The timed swap under the skew chart: the true skew (one machine), the margin, late swaps, and
// on a paced wall the frame-interval jitter.
function swapLine(f) {
  const parts = [];
  if (f.true_skew_ms_p50 !== null) {
    parts.push("true skew p50 " + fmt(f.true_skew_ms_p50, 3) + " p99 " + fmt(f.true_skew_ms_p99, 3) + " ms");
  }
  parts.push(f.swap_margin_ms === null ? "swap untimed (" + f.swap_margin + ")"
    : "margin " + fmt(f.swap_margin_ms, 2) + " ms (" + f.swap_margin + ")");
  parts.push(f.late_swaps + " late swaps");
  if (f.frame_rate !== null) {
    parts.push("paced " + fmt(f.frame_rate, 1) + " fps, jitter p99 " + fmt(f.interval_jitter_ms_p99, 3) + " ms");
  }
  return parts.join(" · ");
}

// A node's card: made once, then only its fields' text changes. Everything a node or its log says
// goes in as text (textContent), never as HTML.
const FIELDS = ["since", "render", "ready", "memory", "clock", "present", "shows", "address", "version", "gpu", "driver"];
function card(box, name) {
  let c = box.querySelector('.node-card[data-node="' + CSS.escape(name) + '"]');
  if (c) return c;
  c = document.createElement("div");
  c.className = "node-card";
  c.dataset.node = name;
  const state = document.createElement("span");
  state.className = "state";
  const title = document.createElement("div");
  title.className = "name";
  title.textContent = name;
  const dl = document.createElement("dl");
  for (const f of FIELDS) {
    const dt = document.createElement("dt");
    dt.textContent = f;
    const dd = document.createElement("dd");
    dd.dataset.field = f;
    dl.append(dt, dd);
  }
  const actions = document.createElement("div");
  actions.className = "actions";
  const restart = document.createElement("button");
  restart.className = "restart";
  restart.textContent = "restart";
  restart.addEventListener("click", async () => {
    if (!confirm("Restart node " + name + "?")) return;
    const r = await post("/api/nodes/" + encodeURIComponent(name) + "/restart", { reason: "restart button of the console's page" });
    if (r && r.ok) {
      const j = await r.json();
      $("control-error").textContent = "";
      c.querySelector(".restart-note").textContent = j.how;
    }
  });
  const note = document.createElement("span");
  note.className = "restart-note note";
  actions.append(restart, note);
  const log = document.createElement("details");
  log.className = "log";
  const summary = document.createElement("summary");
  summary.textContent = "recent log";
  const pre = document.createElement("pre");
  pre.className = "log";
  log.append(summary, pre);
  log.addEventListener("toggle", () => { if (log.open) fetchLog(name, pre); });
  c.append(state, title, dl, actions, log);
  box.appendChild(c);
  return c;
}

// The last lines of a node's log (a daemon the console started), as text.
async function fetchLog(name, pre) {
  try {
    const r = await fetch("/api/nodes/" + encodeURIComponent(name) + "/log?lines=50", { headers: authHeaders, cache: "no-store" });
    const j = await r.json();
    if (!r.ok) { pre.textContent = "log: " + j.error; return; }
    setText(pre, j.local ? j.lines.join("\n") : j.note);
    pre.dataset.source = j.source || "";
  } catch (e) {
    pre.textContent = "log: " + e;
  }
}

// Open logs follow their node every 2 s.
setInterval(() => {
  if (document.hidden) return;
  for (const d of document.querySelectorAll(".node-card details.log[open]")) {
    fetchLog(d.closest(".node-card").dataset.node, d.querySelector("pre.log"));
  }
}, 2000);

function showNodes(s) {
  const box = $("nodes");
  for (const n of s.nodes) {
    const c = card(box, n.name);
    setData(c, "state", n.state);
    setText(c.querySelector(".state"), n.state);
    const what = n.bricks.length ? "bricks " + n.bricks.join(", ") : "tiles " + n.tiles.join(", ");
    const text = {
      since: since(n.since_s) + (n.reason ? " (" + n.reason + ")" : ""),
      render: fmt(n.render_ms, 1) + " ms",
      ready: fmt(n.ready_ms, 1) + " ms",
      memory: (n.rss_kib === null ? "–" : (n.rss_kib / 1024).toFixed(0) + " MiB") +
        (n.resident_volume_bytes === null ? "" : ", volume " + (n.resident_volume_bytes / 1048576).toFixed(1) + " MiB"),
      clock: (n.clock_error_us === null ? "–" : "±" + n.clock_error_us + " µs") +
        (n.late_swaps ? ", " + n.late_swaps + " late swaps" : ""),
      present: n.present === null ? "–" : n.present,
      shows: what,
      address: n.address,
      version: n.version === null ? "–" : n.version,
      gpu: n.adapter === null ? "–" : n.adapter + " (" + n.backend + ")",
      driver: n.driver === null ? "–" : (n.driver + " " + n.driver_info).trim() || "–",
    };
    for (const f of FIELDS) setText(c.querySelector('dd[data-field="' + f + '"]'), text[f]);
    setProp(c.querySelector("button.restart"), "hidden", s.console.read_only);
  }
}

// ---- controls ----
let busy = {}; // control id -> time of the operator's last touch (the status does not overwrite it)
const touched = (id) => busy[id] && performance.now() - busy[id] < 1500;

// The iso slider's step: a power of ten at most a thousandth of the data's span, so a whole
// value of an 8-bit scan (50 of 0..255) or of a CT in Hounsfield units (300) can be set exactly.
function isoStep(span) {
  if (!(span > 0)) return 0.001;
  return Math.pow(10, Math.floor(Math.log10(span / 1000)));
}

function showControls(s) {
  const r = s.render;
  const iso = $("iso");
  const span = s.volume.max - s.volume.min;
  setProp(iso, "min", String(s.volume.min));
  setProp(iso, "max", String(s.volume.max));
  setProp(iso, "step", String(isoStep(span)));
  setText($("iso-min"), fmt(s.volume.min, 3));
  setText($("iso-max"), fmt(s.volume.max, 3));
  if (!touched("iso")) { setProp(iso, "value", String(r.iso)); setText($("iso-value"), fmt(r.iso, 4)); }
  if (!touched("ao-samples")) {
    let k = AO_STEPS.findIndex((x) => x >= r.ao_samples);
    setProp($("ao-samples"), "value", String(k < 0 ? AO_STEPS.length - 1 : k));
    setText($("ao-samples-value"), r.ao_samples + (r.target_frame_ms ? " (governor: " + r.frame_ao_samples + (r.frame_scale > 1 ? " at 1/" + r.frame_scale : "") + ")" : ""));
  }
  if (!touched("ao-method")) setProp($("ao-method"), "value", r.ao_method);
  if (!touched("ibl")) setProp($("ibl"), "value", r.ibl);
  if (!touched("denoise")) setProp($("denoise"), "value", r.denoise);
  if (!touched("exposure")) { setProp($("exposure"), "value", String(r.exposure)); setText($("exposure-value"), fmt(r.exposure, 2)); }
  if (!touched("target-frame-ms") && document.activeElement !== $("target-frame-ms")) {
    setProp($("target-frame-ms"), "value", r.target_frame_ms === null ? "" : String(r.target_frame_ms));
  }
  // Time steps: shown only for a volume that has more than one.
  const t = s.time;
  setProp($("time"), "hidden", t.steps < 2);
  setProp($("step"), "max", String(Math.max(0, t.steps - 1)));
  if (!touched("step")) {
    setProp($("step"), "value", String(t.step));
    setText($("step-value"), t.step + " of 0–" + (t.steps - 1) + (t.waited ? " (a node waited for it)" : ""));
  }
  setProp($("rate"), "min", String(t.min_rate));
  setProp($("rate"), "max", String(t.max_rate));
  if (!touched("rate") && document.activeElement !== $("rate")) setProp($("rate"), "value", String(t.rate));
  setText($("play"), t.playing ? "pause" : "play");
  setText($("orbit"), s.orbit.playing ? "pause orbit" : "play orbit");
  setText($("demo"), s.demo.playing ? "stop demo path" : "start demo path");
  setProp($("demo"), "disabled", !s.demo.path);
  setProp($("demo"), "title", s.demo.path ? s.demo.path : "start the console with --demo-path FILE");
  setText($("identify"), s.wall.identify ? "stop identifying" : "identify screens");
  // A status made before this tab took the lock (it can arrive after the take's answer) says
  // nothing about this tab's lock.
  if (lockId === null || s.console.lock_changes >= lockChanges) showLock(s.console.lock);
}

// ---- the operator lock ----
// The lock id this tab holds (kept for the tab only); its changes carry it in X-Isowall-Lock.
let lockId = sessionStorage.getItem("isowall-lock");
let lockSince = Number(sessionStorage.getItem("isowall-lock-since"));
// The lock's count of holder changes when this tab took it (see `console.lock_changes`).
let lockChanges = Number(sessionStorage.getItem("isowall-lock-changes"));
function dropLock() {
  lockId = null;
  for (const k of ["isowall-lock", "isowall-lock-since", "isowall-lock-changes"]) sessionStorage.removeItem(k);
}
function showLock(l) {
  const mine = lockId !== null && l !== null && l.since_unix_ms === lockSince;
  // Released, lapsed, or taken by another since: this tab's id is no good any more.
  if (lockId !== null && !mine) dropLock();
  setText($("lock-note"), l === null ? "nobody holds the lock: every client may change the wall"
    : (mine ? "you hold the lock" : "locked by " + l.holder) + " since " + new Date(l.since_unix_ms).toLocaleTimeString() +
      " (lapses after " + l.idle_timeout_s.toFixed(0) + " s idle)");
  setProp($("lock-take"), "hidden", mine);
  setProp($("lock-release"), "hidden", !mine);
}
$("lock-take").addEventListener("click", async () => {
  const r = await post("/api/lock", { holder: $("lock-holder").value || "an operator" });
  if (r && r.ok) {
    const j = await r.json();
    lockId = j.lock_id;
    lockSince = j.since_unix_ms;
    lockChanges = j.lock_changes;
    sessionStorage.setItem("isowall-lock", lockId);
    sessionStorage.setItem("isowall-lock-since", String(lockSince));
    sessionStorage.setItem("isowall-lock-changes", String(lockChanges));
    showLock({ holder: j.holder, since_unix_ms: j.since_unix_ms, idle_timeout_s: j.idle_timeout_s });
  }
});
$("lock-release").addEventListener("click", async () => {
  const r = await post("/api/lock/release", {});
  if (r && r.ok) { dropLock(); showLock(null); }
});

// ---- camera bookmarks ----
async function showBookmarks(j) {
  const list = $("bookmark-list");
  list.replaceChildren(...j.bookmarks.map((b) => {
    const o = document.createElement("option");
    o.value = b.name;
    o.textContent = b.name;
    return o;
  }));
  setText($("bookmark-note"), j.error ? "bookmarks file: " + j.error : j.bookmarks.length + " bookmark(s) in " + j.file);
}
async function loadBookmarks() {
  try {
    const r = await fetch("/api/bookmarks", { headers: authHeaders, cache: "no-store" });
    if (r.ok) showBookmarks(await r.json());
  } catch (e) {
    $("bookmark-note").textContent = "bookmarks: " + e;
  }
}
$("bookmark-save").addEventListener("click", async () => {
  const r = await post("/api/bookmarks", { name: $("bookmark-name").value });
  if (r && r.ok) showBookmarks(await r.json());
});
$("bookmark-recall").addEventListener("click", () => post("/api/bookmarks/recall", { name: $("bookmark-list").value }));
$("bookmark-delete").addEventListener("click", async () => {
  const r = await post("/api/bookmarks/delete", { name: $("bookmark-list").value });
  if (r && r.ok) showBookmarks(await r.json());
});
loadBookmarks();

// A change: JSON, with the token and the lock id this tab holds; answers the response (null
// when it could not be sent) and shows a refusal.
async function post(path, body) {
  try {
    const headers = Object.assign({ "Content-Type": "application/json" }, authHeaders);
    if (lockId) headers["X-Isowall-Lock"] = lockId;
    const r = await fetch(path, { method: "POST", headers, body: JSON.stringify(body) });
    if (!r.ok) {
      const e = await r.clone().json().catch(() => ({ error: r.statusText }));
      $("control-error").textContent = (e.field ? e.field + ": " : "") + e.error;
    } else {
      $("control-error").textContent = "";
    }
    return r;
  } catch (e) {
    $("control-error").textContent = String(e);
    return null;
  }
}

// Sliders post while they move, at most every 100 ms, and once more when released.
function throttled(fn) {
  let last = 0, timer = null;
  return () => {
    const wait = 100 - (performance.now() - last);
    clearTimeout(timer);
    if (wait <= 0) { last = performance.now(); fn(); }
    else timer = setTimeout(() => { last = performance.now(); fn(); }, wait);
  };
}

function wire(id, event, fn) {
  const el = $(id);
  el.addEventListener(event, () => { busy[id] = performance.now(); fn(el); });
}

const sendIso = throttled(() => post("/api/render", { iso: Number($("iso").value) }));
wire("iso", "input", (el) => { $("iso-value").textContent = fmt(Number(el.value), 4); sendIso(); });
wire("iso", "change", () => sendIso());
wire("ao-samples", "change", (el) => post("/api/render", { ao_samples: AO_STEPS[Number(el.value)] }));
wire("ao-samples", "input", (el) => { $("ao-samples-value").textContent = AO_STEPS[Number(el.value)]; });
wire("ao-method", "change", (el) => post("/api/render", { ao_method: el.value }));
wire("ibl", "change", (el) => post("/api/render", { ibl: el.value }));
wire("denoise", "change", (el) => post("/api/render", { denoise: el.value }));
const sendExposure = throttled(() => post("/api/render", { exposure: Number($("exposure").value) }));
wire("exposure", "input", (el) => { $("exposure-value").textContent = fmt(Number(el.value), 2); sendExposure(); });
wire("target-frame-ms", "change", (el) =>
  post("/api/render", { target_frame_ms: el.value === "" ? null : Number(el.value) }));
const sendStep = throttled(() => post("/api/time", { step: Number($("step").value) }));
wire("step", "input", (el) => { $("step-value").textContent = el.value; sendStep(); });
wire("step", "change", () => sendStep());
wire("rate", "change", (el) => post("/api/time", { rate: Number(el.value) }));
$("play").addEventListener("click", () => post("/api/time", { play: status && status.time.playing ? "pause" : "play" }));
$("orbit").addEventListener("click", () => post("/api/camera", { orbit: status && status.orbit.playing ? "pause" : "play" }));
$("demo").addEventListener("click", () => post("/api/camera", { demo: status && status.demo.playing ? "stop" : "start" }));
$("identify").addEventListener("click", () => post("/api/identify", { on: !(status && status.wall.identify) }));
$("home").addEventListener("click", () => post("/api/camera", { reset: true, orbit: "pause", demo: "stop" }));
for (const b of document.querySelectorAll("#views button[data-view]")) {
  b.addEventListener("click", () => post("/api/camera", { view: b.dataset.view, orbit: "pause", demo: "stop" }));
}

// Drag on the wall to orbit, wheel to zoom.
(function () {
  const c = $("wall");
  let drag = null;
  c.addEventListener("pointerdown", (e) => { if (status && !status.console.read_only) { drag = { x: e.clientX, y: e.clientY }; c.setPointerCapture(e.pointerId); } });
  c.addEventListener("pointerup", () => { drag = null; });
  c.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    if (Math.abs(dx) + Math.abs(dy) < 4) return;
    drag = { x: e.clientX, y: e.clientY };
    post("/api/camera", { yaw_deg: -dx * 0.3, pitch_deg: dy * 0.3 });
  });
  c.addEventListener("wheel", (e) => {
    if (!status || status.console.read_only) return;
    e.preventDefault();
    post("/api/camera", { zoom: e.deltaY > 0 ? 1.1 : 1 / 1.1 });
  }, { passive: false });
})();

// ---- the wall thumbnail ----
let thumb = null; // the last ImageBitmap

function drawWall() {
  const c = $("wall");
  const ctx = c.getContext("2d");
  if (!status) return;
  const W = status.wall.width, H = status.wall.height;
  const scale = Math.min(c.width / W, c.height / H);
  const ox = (c.width - W * scale) / 2, oy = (c.height - H * scale) / 2;
  ctx.fillStyle = "#000";
  ctx.fillRect(0, 0, c.width, c.height);
  if (thumb) ctx.drawImage(thumb, ox, oy, W * scale, H * scale);
  const state = {};
  for (const n of status.nodes) state[n.name] = n.state;
  for (const t of status.wall.tiles) {
    // The bezels: the screen's frame around its visible pixels.
    const [bl, br, bt, bb] = t.bezel;
    ctx.strokeStyle = "#444";
    ctx.lineWidth = 1;
    ctx.strokeRect(ox + (t.x - bl) * scale + 0.5, oy + (t.y - bt) * scale + 0.5, (t.width + bl + br) * scale - 1, (t.height + bt + bb) * scale - 1);
    const col = { up: "rgba(63,185,80,0.8)", straggling: "rgba(210,153,34,0.9)", down: "rgba(248,81,73,0.95)" }[state[t.node]] || "#888";
    ctx.strokeStyle = col;
    ctx.lineWidth = state[t.node] === "up" ? 1 : 3;
    ctx.strokeRect(ox + t.x * scale + 1, oy + t.y * scale + 1, t.width * scale - 2, t.height * scale - 2);
    ctx.fillStyle = col;
    ctx.font = "11px system-ui, sans-serif";
    ctx.fillText(t.name + " · " + t.node, ox + t.x * scale + 4, oy + t.y * scale + 13);
  }
}

async function thumbLoop() {
  for (;;) {
    const t0 = performance.now();
    if (status && !document.hidden) {
      const c = $("wall");
      const width = Math.max(1, Math.min(status.wall.width, Math.round(c.width)));
      try {
        const r = await fetch("/api/snapshot.png?width=" + width, { headers: authHeaders, cache: "no-store" });
        if (r.ok) {
          const headersAt = performance.now();
          const age = parseFloat(r.headers.get("x-isowall-frame-age-ms"));
          const frame = r.headers.get("x-isowall-frame");
          const blob = await r.blob();
          const bitmap = await createImageBitmap(blob);
          if (thumb) thumb.close();
          thumb = bitmap;
          drawWall();
          // Shown once the browser has painted it.
          await new Promise((res) => requestAnimationFrame(() => requestAnimationFrame(res)));
          const latency = isNaN(age) ? null : age + (performance.now() - headersAt);
          const w = window.isowall;
          w.thumbnails++;
          w.thumbBytes += blob.size;
          w.lastFrame = frame === null ? null : Number(frame);
          w.latencyMs = latency;
          if (latency !== null) { w.latencies.push(latency); if (w.latencies.length > 100) w.latencies.shift(); }
          setText($("latency"), "latency " + fmt(latency, 0) + " ms");
          setText($("thumb-note"), "thumbnail of frame " + frame + " (" + r.headers.get("x-isowall-size") +
            ", downscaled at the nodes), " + (blob.size / 1024).toFixed(1) + " KiB");
          c.dataset.frame = frame;
        }
      } catch (e) {
        $("thumb-note").textContent = "thumbnail: " + e;
      }
    }
    const wait = 1000 / THUMB_HZ - (performance.now() - t0);
    await new Promise((res) => setTimeout(res, Math.max(50, wait)));
  }
}

// ---- charts ----
function chart(c, values, p50, p99, color) {
  const ctx = c.getContext("2d");
  const w = c.width, h = c.height, left = 44, bottom = 16;
  ctx.fillStyle = "#0d1117";
  ctx.fillRect(0, 0, w, h);
  const top = Math.max(1e-3, ...values, p99 || 0) * 1.15;
  const y = (v) => h - bottom - (v / top) * (h - bottom - 6);
  ctx.strokeStyle = "#30363d";
  ctx.fillStyle = "#9aa0a6";
  ctx.font = "10px system-ui, sans-serif";
  ctx.lineWidth = 1;
  for (const v of [0, top / 2, top]) {
    ctx.beginPath(); ctx.moveTo(left, y(v) + 0.5); ctx.lineTo(w, y(v) + 0.5); ctx.stroke();
    ctx.fillText(v.toFixed(v < 10 ? 2 : 0), 2, y(v) + 3);
  }
  ctx.fillText("last " + values.length + " frames", left, h - 3);
  if (values.length > 1) {
    ctx.strokeStyle = color;
    ctx.lineWidth = 1.5;
    ctx.beginPath();
    values.forEach((v, i) => {
      const x = left + (i / (values.length - 1)) * (w - left - 2);
      if (i === 0) ctx.moveTo(x, y(v)); else ctx.lineTo(x, y(v));
    });
    ctx.stroke();
  }
  const mark = (v, label, dash) => {
    if (v === null || v === undefined) return;
    ctx.setLineDash(dash);
    ctx.strokeStyle = "#e6e6e6";
    ctx.lineWidth = 1;
    ctx.beginPath(); ctx.moveTo(left, y(v)); ctx.lineTo(w, y(v)); ctx.stroke();
    ctx.setLineDash([]);
    ctx.fillStyle = "#e6e6e6";
    ctx.fillText(label + " " + v.toFixed(2), w - 80, y(v) - 3);
  };
  mark(p50, "p50", [4, 3]);
  mark(p99, "p99", [1, 2]);
}

document.addEventListener("visibilitychange", () => { if (!document.hidden && status) { charted = wallKey = null; show(status); } });
connect();
thumbLoop();

// The full-resolution snapshot: a plain link without a token; with one, fetched with its header
// and saved from memory (a link cannot carry a header, and the token stays out of URLs).
$("download").addEventListener("click", async (ev) => {
  if (!token) return;
  ev.preventDefault();
  try {
    const r = await fetch("/api/snapshot.png?download=1", { headers: authHeaders, cache: "no-store" });
    if (!r.ok) {
      const e = await r.json().catch(() => ({ error: r.statusText }));
      $("control-error").textContent = "snapshot: " + e.error;
      return;
    }
    const url = URL.createObjectURL(await r.blob());
    const a = document.createElement("a");
    a.href = url;
    a.download = "isowall-frame-" + (r.headers.get("x-isowall-frame") || "0") + ".png";
    a.click();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
  } catch (e) {
    $("control-error").textContent = "snapshot: " + String(e);
  }
});
