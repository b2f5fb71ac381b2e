// The Isowall operator console: live status over the /api/live WebSocket, the wall thumbnail
// fetched at THUMB_HZ from /api/snapshot.png?width=, charts drawn by hand on canvases, and the
// controls posting to /api/render, /api/camera and /api/time. No build step, no libraries.
"use strict";

const THUMB_HZ = 2;
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
const withToken = (url) => (token ? url + (url.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token) : url);

const $ = (id) => document.getElementById(id);
let status = null;
// What the page measured, for the operator and for tests.
window.isowall = { thumbnails: 0, thumbBytes: 0, statusMessages: 0, lastFrame: null, latencyMs: null, latencies: [] };

// ---- live status ----
function connect() {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  const ws = new WebSocket(withToken(proto + "//" + location.host + "/api/live?hz=4"));
  ws.onopen = () => { $("link").textContent = "live"; $("link").className = "good"; };
  ws.onmessage = (ev) => {
    window.isowall.statusMessages++;
    status = JSON.parse(ev.data);
    show(status);
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

function show(s) {
  $("wall-name").textContent = s.wall.name + " (" + s.wall.width + "×" + s.wall.height + ", " + s.wall.mode + " space)";
  $("fps").textContent = fmt(s.frame.fps, 1) + " fps";
  $("frame").textContent = "frame " + s.frame.id;
  $("ro-badge").hidden = !s.console.read_only;
  $("controls").hidden = s.console.read_only;
  showNodes(s);
  showControls(s);
  chart($("chart-frame"), s.frame.frame_ms, s.frame.frame_ms_p50, s.frame.frame_ms_p99, "#58a6ff");
  chart($("chart-skew"), s.frame.skew_ms, s.frame.skew_ms_p50, s.frame.skew_ms_p99, "#d29922");
  drawWall();
}

function showNodes(s) {
  const box = $("nodes");
  for (const n of s.nodes) {
    let card = box.querySelector('.node-card[data-node="' + CSS.escape(n.name) + '"]');
    if (!card) {
      card = document.createElement("div");
      card.className = "node-card";
      card.dataset.node = n.name;
      box.appendChild(card);
    }
    card.dataset.state = n.state;
    const what = n.bricks.length ? "bricks " + n.bricks.join(", ") : "tiles " + n.tiles.join(", ");
    card.innerHTML =
      '<span class="state">' + n.state + "</span>" +
      '<div class="name">' + escapeHtml(n.name) + "</div>" +
      "<dl>" +
      "<dt>since</dt><dd>" + since(n.since_s) + (n.reason ? " (" + escapeHtml(n.reason) + ")" : "") + "</dd>" +
      "<dt>render</dt><dd>" + fmt(n.render_ms, 1) + " ms</dd>" +
      "<dt>ready</dt><dd>" + fmt(n.ready_ms, 1) + " ms</dd>" +
      "<dt>memory</dt><dd>" + (n.rss_kib === null ? "–" : (n.rss_kib / 1024).toFixed(0) + " MiB") +
      (n.resident_volume_bytes === null ? "" : ", volume " + (n.resident_volume_bytes / 1048576).toFixed(1) + " MiB") + "</dd>" +
      "<dt>shows</dt><dd>" + escapeHtml(what) + "</dd>" +
      "<dt>address</dt><dd>" + escapeHtml(n.address) + "</dd>" +
      "</dl>";
  }
}

function escapeHtml(t) {
  return String(t).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
}

// ---- controls ----
let busy = {}; // control id -> time of the operator's last touch (the status does not overwrite it)
const touched = (id) => busy[id] && performance.now() - busy[id] < 1500;

function showControls(s) {
  const r = s.render;
  const iso = $("iso");
  const span = s.volume.max - s.volume.min;
  iso.min = s.volume.min;
  iso.max = s.volume.max;
  iso.step = span > 0 ? span / 200 : 0.001;
  $("iso-min").textContent = fmt(s.volume.min, 3);
  $("iso-max").textContent = fmt(s.volume.max, 3);
  if (!touched("iso")) { iso.value = r.iso; $("iso-value").textContent = fmt(r.iso, 4); }
  if (!touched("ao-samples")) {
    let k = AO_STEPS.findIndex((x) => x >= r.ao_samples);
    $("ao-samples").value = k < 0 ? AO_STEPS.length - 1 : k;
    $("ao-samples-value").textContent = r.ao_samples + (r.target_frame_ms ? " (governor: " + r.frame_ao_samples + (r.frame_scale > 1 ? " at 1/" + r.frame_scale : "") + ")" : "");
  }
  if (!touched("ao-method")) $("ao-method").value = r.ao_method;
  if (!touched("ibl")) $("ibl").value = r.ibl;
  if (!touched("exposure")) { $("exposure").value = r.exposure; $("exposure-value").textContent = fmt(r.exposure, 2); }
  if (!touched("target-frame-ms") && document.activeElement !== $("target-frame-ms")) {
    $("target-frame-ms").value = r.target_frame_ms === null ? "" : r.target_frame_ms;
  }
  // Time steps: shown only for a volume that has more than one.
  const t = s.time;
  $("time").hidden = t.steps < 2;
  $("step").max = Math.max(0, t.steps - 1);
  if (!touched("step")) {
    $("step").value = t.step;
    $("step-value").textContent = t.step + " of 0–" + (t.steps - 1) + (t.waited ? " (a node waited for it)" : "");
  }
  $("rate").min = t.min_rate;
  $("rate").max = t.max_rate;
  if (!touched("rate") && document.activeElement !== $("rate")) $("rate").value = t.rate;
  $("play").textContent = t.playing ? "pause" : "play";
  $("orbit").textContent = s.orbit.playing ? "pause orbit" : "play orbit";
  $("demo").textContent = s.demo.playing ? "stop demo path" : "start demo path";
  $("demo").disabled = !s.demo.path;
  $("demo").title = s.demo.path ? s.demo.path : "start the console with --demo-path FILE";
  $("download").href = withToken("/api/snapshot.png?download=1");
}

async function post(path, body) {
  try {
    const r = await fetch(path, {
      method: "POST",
      headers: Object.assign({ "Content-Type": "application/json" }, authHeaders),
      body: JSON.stringify(body),
    });
    if (!r.ok) {
      const e = await r.json().catch(() => ({ error: r.statusText }));
      $("control-error").textContent = (e.field ? e.field + ": " : "") + e.error;
    } else {
      $("control-error").textContent = "";
    }
  } catch (e) {
    $("control-error").textContent = String(e);
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
$("home").addEventListener("click", () => post("/api/camera", { reset: true, orbit: "pause", demo: "stop" }));

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
    if (status) {
      const c = $("wall");
      const width = Math.max(1, Math.min(status.wall.width, Math.round(c.width)));
      try {
        const r = await fetch(withToken("/api/snapshot.png?width=" + width), { headers: authHeaders, cache: "no-store" });
        if (r.ok) {
          const headersAt = performance.now();
          const age = parseFloat(r.headers.get("x-isowall-frame-age-ms"));
          const frame = r.headers.get("x-isowall-frame");
          const blob = await r.blob();
          thumb = await createImageBitmap(blob);
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
          $("latency").textContent = "latency " + fmt(latency, 0) + " ms";
          $("thumb-note").textContent = "thumbnail of frame " + frame + " (" + r.headers.get("x-isowall-size") +
            ", downscaled at the nodes), " + (blob.size / 1024).toFixed(1) + " KiB";
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

connect();
thumbLoop();
