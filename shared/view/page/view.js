// Tele-Touch live view: plain JavaScript and canvas, no build step, no dependencies.
// Connects to the WebSocket beside this page ("ws" relative to the page URL), takes one
// snapshot message at a time (see shared/view/server.py) and redraws. A session token for
// the relay's view is read from the URL fragment (#session=S&token=T), never from the query,
// so it is not sent to any server in a request line.
"use strict";

const STALE_MS = 500;        // older data is drawn dimmed and labelled stale
// no snapshot for this long (and for 3 snapshot periods) while connected: the page says
// "no data" and dims everything (a stream can stop with its socket still open)
const NO_DATA_MS = STALE_MS;
const FRESH_CHECK_MS = 100;  // how often the page checks that snapshots still arrive
const CHART_S = 30;          // chart window
const STAGE_COLOURS = ["#58a6ff", "#3fb950", "#d29922", "#bc8cff", "#ff7b72", "#39c5cf",
  "#e3b341", "#8b949e", "#f778ba", "#a5d6ff", "#7ee787", "#ffa657"];

// State the page keeps; also read by the browser test (window.teletouchView).
const state = {
  messages: 0, pinUpdates: 0, lastPins: "", trail: [], trailNext: 0, analysis: null,
  findings: [], latencySamples: 0, live: null, mapLayer: "relief", connected: false,
  stageNames: [], receivedAt: [], replay: null, ws: null,
  // freshness: when the last snapshot arrived (performance.now() ms; the socket's opening
  // until the first), the last intervals between snapshots, and whether all is dimmed
  lastMessageAt: 0, intervals: [], noData: false, dimmed: false, trailResets: 0,
  analysisStopped: false, mapInfo: "",
};
window.teletouchView = state;

// ------------------------------------------------------------------ helpers

function $(id) { return document.getElementById(id); }

function setBadge(id, text, cls) {
  const el = $(id);
  el.textContent = text;
  el.className = "badge" + (cls ? " " + cls : "");
}

// what is drawn is not current (socket closed, or no snapshot for too long): dim it all
function dimAll(on) {
  state.dimmed = on;
  for (const c of document.querySelectorAll("canvas")) c.classList.toggle("stale", on);
  for (const id of ["link", "safe", "analysis", "station"]) $(id).classList.toggle("stale", on);
}

function b64bytes(text) {
  const bin = atob(text);
  const out = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
  return out;
}

// a perceptual-ish dark-blue -> teal -> yellow ramp, t in [0, 1]
const RAMP = [[13, 8, 135], [84, 2, 163], [139, 10, 165], [185, 50, 137], [219, 92, 104],
  [244, 136, 73], [254, 188, 43], [240, 249, 33]];
function ramp(t) {
  const x = Math.min(1, Math.max(0, t)) * (RAMP.length - 1);
  const i = Math.min(RAMP.length - 2, Math.floor(x));
  const f = x - i;
  const a = RAMP[i], b = RAMP[i + 1];
  return [a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f, a[2] + (b[2] - a[2]) * f];
}

// an image from base64 bytes (0 = no data, 1..255 = lo..hi), row 0 = lowest y
function quantisedImage(enc, flipY) {
  const bytes = b64bytes(enc.data);
  const img = new ImageData(enc.w, enc.h);
  for (let r = 0; r < enc.h; r++) {
    const dst = flipY ? enc.h - 1 - r : r;
    for (let c = 0; c < enc.w; c++) {
      const v = bytes[r * enc.w + c];
      const o = (dst * enc.w + c) * 4;
      if (v === 0) { img.data[o + 3] = 0; continue; }
      const [R, G, B] = ramp((v - 1) / 254);
      img.data[o] = R; img.data[o + 1] = G; img.data[o + 2] = B; img.data[o + 3] = 255;
    }
  }
  return img;
}

function drawImageScaled(ctx, img, x, y, w, h) {
  const tmp = document.createElement("canvas");
  tmp.width = img.width; tmp.height = img.height;
  tmp.getContext("2d").putImageData(img, 0, 0);
  ctx.imageSmoothingEnabled = false;
  ctx.drawImage(tmp, x, y, w, h);
}

// ------------------------------------------------------------------ charts

class Chart {
  constructor(canvas, opts) {
    this.canvas = canvas; this.ctx = canvas.getContext("2d");
    this.series = new Map(); this.opts = opts || {};
  }
  push(name, t, v, colour) {
    if (v === null || v === undefined || !isFinite(v)) return;
    let s = this.series.get(name);
    if (!s) { s = { pts: [], colour: colour || "#ccc" }; this.series.set(name, s); }
    s.pts.push([t, v]);
    while (s.pts.length && s.pts[0][0] < t - CHART_S) s.pts.shift();
  }
  draw(now) {
    const { ctx, canvas } = this;
    const W = canvas.width, H = canvas.height;
    ctx.clearRect(0, 0, W, H);
    let lo = Infinity, hi = -Infinity;
    for (const s of this.series.values()) for (const [, v] of s.pts) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
    if (this.opts.zero) lo = Math.min(lo, 0);
    if (!isFinite(lo)) return;
    if (hi - lo < 1e-9) { hi += 1; lo -= 1; }
    const pad = (hi - lo) * 0.08; lo -= pad; hi += pad;
    const X = (t) => W - ((now - t) / CHART_S) * W;
    const Y = (v) => H - 12 - ((v - lo) / (hi - lo)) * (H - 16);
    ctx.font = "10px system-ui"; ctx.fillStyle = "#8a96a3";
    ctx.fillText(hi.toFixed(hi - lo < 5 ? 2 : 0), 2, 10);
    ctx.fillText(lo.toFixed(hi - lo < 5 ? 2 : 0), 2, H - 2);
    for (const s of this.series.values()) {
      ctx.strokeStyle = s.colour; ctx.lineWidth = 1.3; ctx.beginPath();
      s.pts.forEach(([t, v], i) => (i ? ctx.lineTo(X(t), Y(v)) : ctx.moveTo(X(t), Y(v))));
      ctx.stroke();
    }
  }
}

const charts = {
  ee: new Chart($("chart-ee")), force: new Chart($("chart-force"), { zero: true }),
  latency: new Chart($("chart-latency"), { zero: true }),
  state: new Chart($("chart-state"), { zero: true }),
};

// ------------------------------------------------------------------ panels

function drawPins(pins, replay) {
  const cv = $("pins"), ctx = cv.getContext("2d");
  const W = cv.width, H = cv.height, cell = Math.min(W, H) / 4;
  ctx.clearRect(0, 0, W, H);
  if (!pins || !pins.commanded_mm) {
    ctx.fillStyle = "#8a96a3"; ctx.font = "14px system-ui";
    $("pins-age").textContent = "";
    ctx.fillText(pins ? "no pin command (safe state or not started)"
      : replay ? "pins: no recent sample recorded" : "pins: shown at the local station only", 10, H / 2);
    return;
  }
  const cmd = pins.commanded_mm, meas = pins.measured_mm, k = pins.stiffness_k, f = pins.friction;
  // bar scale: the smallest of 0.5, 1, 2, 5 mm that holds every height shown
  const top = Math.max(...cmd.map((v) => v || 0), ...(meas || []).map((v) => v || 0));
  const full = [0.5, 1, 2, 5].find((v) => top <= v) || 5;
  for (let i = 0; i < 16; i++) {
    const row = Math.floor(i / 4), col = i % 4;
    // row 0 is the pins' -y row: draw +y up
    const x = col * cell, y = (3 - row) * cell;
    const kk = k ? (k[i] - 0.5) / 0.5 : 0;
    const shade = Math.round(70 - 45 * kk);
    ctx.fillStyle = `rgb(${shade},${shade + 6},${shade + 14})`;
    ctx.fillRect(x + 2, y + 2, cell - 4, cell - 4);
    const bw = cell * 0.22, base = y + cell - 8, span = cell - 26;
    const hc = Math.max(0, Math.min(full, cmd[i] || 0)) / full * span;
    ctx.strokeStyle = "#58a6ff"; ctx.lineWidth = 2;
    ctx.strokeRect(x + cell * 0.25, base - hc, bw, hc);
    if (meas) {
      const hm = Math.max(0, Math.min(full, meas[i] || 0)) / full * span;
      ctx.fillStyle = "#f0883e";
      ctx.fillRect(x + cell * 0.53, base - hm, bw, hm);
    }
    ctx.fillStyle = "#dde3ea"; ctx.font = "11px system-ui";
    ctx.fillText(`${(cmd[i] || 0).toFixed(2)}`, x + 6, y + 14);
    if (meas) { ctx.fillStyle = "#f0883e"; ctx.fillText(`${(meas[i] || 0).toFixed(2)}`, x + cell - 36, y + 14); }
    ctx.fillStyle = "#8a96a3";
    ctx.fillText(`k ${k ? k[i].toFixed(2) : "?"} f ${f ? f[i].toFixed(2) : "?"}`, x + 6, y + 28);
  }
  const age = pins.measured_age_ms;
  $("pins-age").textContent = `bars 0-${full} mm; ` + (age === null ? "no feedback" : (age > STALE_MS ? `feedback STALE ${age.toFixed(0)} ms` : `feedback ${age.toFixed(0)} ms old`));
  cv.classList.toggle("stale", age === null || age > STALE_MS);
}

function drawPatch(patch) {
  const cv = $("patch"), ctx = cv.getContext("2d");
  const W = cv.width, H = cv.height;
  ctx.clearRect(0, 0, W, H);
  if (!patch) {
    ctx.fillStyle = "#8a96a3"; ctx.font = "14px system-ui";
    ctx.fillText("no tactile frame yet", 10, H / 2);
    $("patch-info").textContent = "";
    return;
  }
  const scale = Math.min(W / patch.w, H / patch.h);
  const pw = patch.w * scale, ph = patch.h * scale;
  const ox = (W - pw) / 2, oy = (H - ph) / 2;
  drawImageScaled(ctx, quantisedImage(patch, true), ox, oy, pw, ph);
  if (patch.window) {
    const [c0, r0, c1, r1] = patch.window;
    // columns/rows are sample indices; sample i covers [i-0.5, i+0.5]; +y drawn up
    const x0 = ox + (c0 + 0.5) * scale, x1 = ox + (c1 + 0.5) * scale;
    const y0 = oy + ph - (r1 + 0.5) * scale, y1 = oy + ph - (r0 + 0.5) * scale;
    ctx.strokeStyle = "#ffffff"; ctx.lineWidth = 2; ctx.setLineDash([5, 3]);
    ctx.strokeRect(x0, y0, x1 - x0, y1 - y0); ctx.setLineDash([]);
  }
  const stale = patch.age_ms > STALE_MS;
  cv.classList.toggle("stale", stale);
  $("patch-info").textContent = `seq ${patch.seq}, ${patch.lo_mm?.toFixed(3)}..${patch.hi_mm?.toFixed(3)} mm, ` +
    `${patch.contact ? "contact" : "no contact"}, ${patch.force_n?.toFixed(2)} N, ` +
    (stale ? `STALE ${patch.age_ms.toFixed(0)} ms` : `${patch.age_ms.toFixed(0)} ms old`);
}

function workspaceTransform(live, W, H) {
  let lo = [-30, -30], hi = [30, 30];
  const an = state.analysis;
  if (an && an.grid && an.relief) {
    lo = [an.grid.x0_mm, an.grid.y0_mm];
    hi = [an.grid.x0_mm + an.relief.w * an.grid.cell_mm, an.grid.y0_mm + an.relief.h * an.grid.cell_mm];
  } else if (live && live.workspace_mm) {
    lo = [live.workspace_mm[0][0] - 10, live.workspace_mm[0][1] - 10];
    hi = [live.workspace_mm[1][0] + 10, live.workspace_mm[1][1] + 10];
  }
  const s = Math.min(W / (hi[0] - lo[0]), H / (hi[1] - lo[1]));
  const ox = (W - (hi[0] - lo[0]) * s) / 2, oy = (H - (hi[1] - lo[1]) * s) / 2;
  return { s, lo, hi, X: (x) => ox + (x - lo[0]) * s, Y: (y) => H - oy - (y - lo[1]) * s };
}

function drawWorkspace() {
  const live = state.live;
  const cv = $("workspace"), ctx = cv.getContext("2d");
  const W = cv.width, H = cv.height;
  ctx.clearRect(0, 0, W, H);
  const T = workspaceTransform(live, W, H);
  const an = state.analysis;
  if (an && an.grid) {
    const enc = state.mapLayer === "relief" ? an.relief : an.stiffness_n_per_mm;
    if (enc) {
      const cell = an.grid.cell_mm;
      // cell centres at x0 + i*cell: the image spans [x0 - cell/2, x0 + (w - 1/2) cell]
      const x0 = T.X(an.grid.x0_mm - cell / 2), y1 = T.Y(an.grid.y0_mm - cell / 2);
      const x1 = T.X(an.grid.x0_mm + (enc.w - 0.5) * cell), y0 = T.Y(an.grid.y0_mm + (enc.h - 0.5) * cell);
      ctx.globalAlpha = state.analysisStopped ? 0.3 : 0.85;
      drawImageScaled(ctx, quantisedImage(enc, true), x0, y0, x1 - x0, y1 - y0);
      ctx.globalAlpha = 1;
    }
  }
  if (live && live.workspace_mm) {
    const [lo, hi] = live.workspace_mm;
    ctx.strokeStyle = "#444c56"; ctx.lineWidth = 1;
    ctx.strokeRect(T.X(lo[0]), T.Y(hi[1]), (hi[0] - lo[0]) * T.s, (hi[1] - lo[1]) * T.s);
  }
  // trajectory: grey while hovering, white while in contact
  const tr = state.trail;
  ctx.lineWidth = 1;
  for (let i = 1; i < tr.length; i++) {
    const a = tr[i - 1], b = tr[i];
    ctx.strokeStyle = b[3] ? "rgba(255,255,255,0.8)" : "rgba(140,150,160,0.45)";
    ctx.beginPath(); ctx.moveTo(T.X(a[0]), T.Y(a[1])); ctx.lineTo(T.X(b[0]), T.Y(b[1])); ctx.stroke();
  }
  const probe = live && live.probe && live.probe.phantom_mm;
  let probeInfo = "";
  if (probe) {
    // platform_age_ms: null = age unknown (stale); absent = the source gives no age
    const age = live.probe.platform_age_ms;
    const stale = age === null || (typeof age === "number" && age > STALE_MS);
    const px = T.X(probe[0]), py = T.Y(probe[1]);
    ctx.beginPath(); ctx.arc(px, py, 5, 0, 2 * Math.PI);
    if (stale) {  // hollow and dim: where the probe was, not where it is
      ctx.strokeStyle = "rgba(88,166,255,0.55)"; ctx.lineWidth = 1.5; ctx.stroke();
      ctx.fillStyle = "#8a96a3"; ctx.font = "bold 11px system-ui";
      ctx.fillText("STALE", px + 8, py + 4);
    } else {
      ctx.fillStyle = "#58a6ff"; ctx.fill();
    }
    probeInfo = typeof age === "number" ? (stale ? `probe STALE ${age.toFixed(0)} ms` : `probe ${age.toFixed(0)} ms old`)
      : age === null ? "probe STALE (age unknown)" : "";
  }
  $("probe-info").textContent = probeInfo;
  // the analysis process has stopped: its last findings are drawn dimmed (not current)
  if (state.analysisStopped) ctx.globalAlpha = 0.4;
  for (const f of state.findings) {
    const r = Math.max(4, f.equivalent_radius_mm * T.s);
    // malignant red, benign green, "uncertain" (a finding not fully covered) amber
    ctx.strokeStyle = f.kind === "malignant" ? "#f85149"
      : f.kind === "uncertain" ? "#d29922" : "#3fb950";
    ctx.lineWidth = 2.5;
    ctx.beginPath(); ctx.arc(T.X(f.center_mm[0]), T.Y(f.center_mm[1]), r, 0, 2 * Math.PI); ctx.stroke();
    ctx.fillStyle = ctx.strokeStyle; ctx.font = "bold 12px system-ui";
    ctx.fillText(`${f.kind} ${(100 * (f.confidence ?? 0)).toFixed(0)}%`, T.X(f.center_mm[0]) + r + 3, T.Y(f.center_mm[1]) - 3);
  }
  ctx.globalAlpha = 1;
}

function updateFindings(an) {
  state.analysis = an;
  state.findings = an.findings || [];
  const ul = $("findings");
  ul.textContent = "";
  for (const f of state.findings) {
    const li = document.createElement("li");
    li.dataset.kind = f.kind;
    li.textContent = `${f.kind} at (${f.center_mm[0].toFixed(1)}, ${f.center_mm[1].toFixed(1)}) mm, ` +
      `r ${f.equivalent_radius_mm.toFixed(1)} mm, severity rank ${f.severity_rank}, ` +
      `confidence ${(100 * (f.confidence ?? 0)).toFixed(0)}%`;
    ul.appendChild(li);
  }
  state.mapInfo = an.state === "ok"
    ? `analysis run ${an.run}: ${an.frames_used} contact frames of ${an.frames}, ${an.seconds.toFixed(2)} s; ` +
      `${state.findings.length} finding(s); confidence = share of the last 5 runs that found it`
    : `analysis run ${an.run}: ${an.reason || an.state}`;
}

// the analysis badge, the map text and the findings' dimming, from every snapshot: a dead
// analysis process (analysis_state.alive false) leaves its last findings, no longer updated
function updateAnalysisStatus(live) {
  const as = live.analysis_state;
  const stopped = !!as && as.alive === false;
  state.analysisStopped = stopped;
  const n = state.findings.length;
  if (stopped) setBadge("analysis", "analysis stopped", "bad");
  else if (state.analysis) setBadge("analysis", `analysis: ${n} finding(s)`, n ? "ok" : "");
  else if (!as) setBadge("analysis", "analysis: runs at the local station", "");
  else setBadge("analysis", "analysis: no result yet", "");
  $("findings").classList.toggle("stale", stopped);
  $("map-info").textContent = stopped
    ? "ANALYSIS STOPPED: not updated any more; " + (state.mapInfo ? "the last result: " + state.mapInfo : "no result")
    : state.mapInfo;
}

function updateCharts(live, now) {
  const p = live.probe || {};
  if (p.end_effector_mm && p.arm_age_ms !== null && p.arm_age_ms < STALE_MS) {
    charts.ee.push("x", now, p.end_effector_mm[0], "#58a6ff");
    charts.ee.push("y", now, p.end_effector_mm[1], "#3fb950");
    charts.ee.push("z", now, p.end_effector_mm[2], "#d29922");
    charts.force.push("arm", now, p.end_effector_force_n, "#ff7b72");
  }
  if (live.patch && live.patch.age_ms < STALE_MS) charts.force.push("frame", now, live.patch.force_n, "#bc8cff");
  const lat = live.latency;
  if (lat && lat.age_ms < STALE_MS) {
    state.latencySamples++;
    for (const [name, ms] of Object.entries(lat.stages_ms)) {
      let idx = state.stageNames.indexOf(name);
      if (idx < 0) { state.stageNames.push(name); idx = state.stageNames.length - 1; }
      charts.latency.push(name, now, ms, STAGE_COLOURS[idx % STAGE_COLOURS.length]);
    }
    charts.latency.push("end_to_end", now, lat.end_to_end_ms, "#ffffff");
    // built from text nodes, never parsed as HTML: stage names come from messages (and
    // from a recording's file in a replay)
    const fmt = (v) => (typeof v === "number" && isFinite(v) ? v.toFixed(1) : "-");
    const legend = $("latency-legend");
    legend.replaceChildren();
    state.stageNames.forEach((n, i) => {
      const span = document.createElement("span");
      span.style.color = STAGE_COLOURS[i % STAGE_COLOURS.length];
      span.textContent = `${n} ${fmt(lat.stages_ms[n])}`;
      legend.append(span, " \u00b7 ");
    });
    legend.append(`end to end ${fmt(lat.end_to_end_ms)} ms`);
  }
  const linkUp = live.link && live.link.state === "up" ? 1 : 0;
  charts.state.push("link", now, linkUp * 0.9, "#3fb950");
  charts.state.push("safe", now, live.safe && live.safe.reason ? 1 : 0, "#f85149");
  for (const c of Object.values(charts)) c.draw(now);
}

// a replay: the page says so (title, banner, badges) and offers play / pause
function updateReplay(rp) {
  state.replay = rp;
  $("replay-bar").hidden = false;
  document.title = "Tele-Touch REPLAY (not live)";
  document.querySelector("header h1").textContent = "Tele-Touch replay";
  const status = rp.ended ? "ended" : rp.paused ? "paused" : rp.started ? "playing" : "starting";
  setBadge("conn", `REPLAY ${status}, not live`, "warn");
  const btn = $("replay-toggle");
  btn.textContent = rp.paused ? "play" : "pause";
  btn.disabled = !!rp.ended;
  $("replay-position").textContent = `${(rp.position_s ?? 0).toFixed(1)} / ${(rp.duration_s ?? 0).toFixed(1)} s` +
    ` at ${rp.speed}x` + (rp.ended ? " (ended)" : rp.paused ? " (paused)" : "");
  $("replay-progress").value = rp.duration_s ? Math.min(1, rp.position_s / rp.duration_s) : 1;
  const when = new Date(rp.recorded_at_us / 1000);
  $("replay-info").textContent = `${rp.file}: ${rp.station} station, recorded ${when.toISOString().replace("T", " ").slice(0, 19)} UTC` +
    (rp.complete ? "" : " (file cut short: played to its last complete chunk)") + "; ages are in recorded time";
}

function pruneReceived(wall) {
  while (state.receivedAt.length && state.receivedAt[0] < wall - 1) state.receivedAt.shift();
}

function updateRateBadge() {
  const live = state.live;
  const loop = (live && live.display_loop) || {};
  const hz = `view ${state.receivedAt.length} Hz`;
  // without data the loop's rate is not known any more
  setBadge("rate", live && !live.replay && !state.noData ? `${hz}, loop ${loop.rate_hz ?? "?"} Hz` : hz,
    state.noData ? "bad" : "");
}

function onSnapshot(msg) {
  const nowMs = performance.now();
  const wall = nowMs / 1000;
  // charts run on the replay's recorded time in a replay (they stand still while paused)
  const now = msg.live && msg.live.replay ? msg.live.replay.position_s : wall;
  state.messages++;
  if (state.messages > 1 && state.lastMessageAt) {
    state.intervals.push(nowMs - state.lastMessageAt);
    if (state.intervals.length > 20) state.intervals.shift();
  }
  state.lastMessageAt = nowMs;
  state.noData = false;
  if (state.dimmed) dimAll(false);  // fresh data: the panels say their own ages again
  state.receivedAt.push(wall);
  pruneReceived(wall);
  const live = msg.live;
  state.live = live;
  if (msg.trail) {
    const { from, points } = msg.trail;
    // the server sends a browser the trail from its oldest point at each connection: after
    // a reconnect (or a restarted source) the trail starts again, never appended twice
    if (from < state.trailNext) { state.trail = []; state.trailResets++; }
    else if (from > state.trailNext) state.trailGaps = (state.trailGaps || 0) + 1; // oldest points dropped at the source
    for (const p of points) state.trail.push(p);
    state.trailNext = from + points.length;
  }
  if (msg.analysis) updateFindings(msg.analysis);
  updateAnalysisStatus(live);
  const pinsKey = live.pins && live.pins.commanded_mm ? live.pins.commanded_mm.join(",") + "|" + (live.pins.measured_mm || []).join(",") : "";
  if (pinsKey && pinsKey !== state.lastPins) { state.pinUpdates++; state.lastPins = pinsKey; }
  drawPins(live.pins, !!live.replay);
  drawPatch(live.patch);
  drawWorkspace();
  updateCharts(live, now);
  if (live.replay) updateReplay(live.replay); else setBadge("conn", "live", "ok");
  const link = live.link || {};
  if (link.state === "replay") setBadge("link", "link: recorded session", "warn"); else
  setBadge("link", link.state === "up" ? "link up" : link.state === "none" ? "no relay link" : `link DOWN ${(link.down_s || 0).toFixed(1)} s`,
    link.state === "up" ? "ok" : link.state === "none" ? "" : "bad");
  const safe = live.safe && live.safe.reason;
  if (live.replay && live.safe && live.safe.known === false) setBadge("safe", "recorded safe state: unknown (no recent pins sample)", "");
  else if (live.safe && live.safe.known === false) setBadge("safe", "pins' safe state: known at the local station", "");
  else if (live.replay) setBadge("safe", safe ? `recorded SAFE STATE: ${safe}` : "recorded: rendering", safe ? "bad" : "");
  else setBadge("safe", safe ? `SAFE STATE: ${safe}` : "rendering", safe ? "bad" : "ok");
  updateRateBadge();
  $("station").textContent = `${live.replay ? "replay of the " : ""}${live.station}${live.session ? " session " + live.session : ""}, ${live.view ? live.view.clients : "?"} viewer(s)`;
}

// ------------------------------------------------------------------ connection

// a %-escape that does not decode is kept as written (never an exception before the hello)
function decodePart(text) {
  try { return decodeURIComponent(text); } catch (e) { return text; }
}

// #session=S&token=T: each value runs to the next "&" ("=" inside a value is kept)
function hashParams() {
  const out = Object.create(null);
  for (const part of location.hash.replace(/^#/, "").split("&")) {
    if (!part) continue;
    const eq = part.indexOf("=");
    const k = eq < 0 ? part : part.slice(0, eq);
    out[decodePart(k)] = eq < 0 ? "" : decodePart(part.slice(eq + 1));
  }
  return out;
}

// while connected: no snapshot for NO_DATA_MS and 3 snapshot periods -> "no data", dimmed
function snapshotPeriodMs() {
  if (!state.intervals.length) return 0;
  const sorted = [...state.intervals].sort((a, b) => a - b);
  return sorted[Math.floor(sorted.length / 2)];
}

function checkFresh() {
  const nowMs = performance.now();
  pruneReceived(nowMs / 1000);
  if (state.connected) {
    const silentMs = nowMs - state.lastMessageAt;
    if (silentMs > Math.max(NO_DATA_MS, 3 * snapshotPeriodMs())) {
      state.noData = true;
      if (!state.dimmed) dimAll(true);
      setBadge("conn", `no data ${(silentMs / 1000).toFixed(1)} s`, "bad");
    }
  }
  updateRateBadge();
}

function connect() {
  const url = new URL("ws", location.href);
  url.protocol = location.protocol === "https:" ? "wss:" : "ws:";
  url.hash = ""; url.search = "";
  const ws = new WebSocket(url);
  state.ws = ws;
  ws.onopen = () => {
    const p = hashParams();
    if (p.token) ws.send(JSON.stringify({ type: "hello", session: p.session || "", token: p.token }));
    // what is drawn stays dimmed until the first snapshot of this connection
    state.connected = true; setBadge("conn", "connected", "");
    state.lastMessageAt = performance.now(); state.intervals = [];
  };
  ws.onmessage = (ev) => {
    let msg;
    try { msg = JSON.parse(ev.data); } catch (e) { return; }
    if (msg.type === "snapshot") onSnapshot(msg);
  };
  ws.onclose = (ev) => {
    state.connected = false; state.noData = false;
    // what is drawn is no longer live: dim it until fresh snapshots arrive
    dimAll(true);
    setBadge("conn", ev.code === 4001 ? "refused: session token needed (#session=S&token=T)" : "disconnected; retrying", "bad");
    if (ev.code !== 4001) setTimeout(connect, 1000);
  };
}

for (const [id, layer] of [["show-relief", "relief"], ["show-stiffness", "stiffness"]]) {
  $(id).addEventListener("click", () => {
    state.mapLayer = layer;
    $("show-relief").setAttribute("aria-pressed", String(layer === "relief"));
    $("show-stiffness").setAttribute("aria-pressed", String(layer === "stiffness"));
    drawWorkspace();
  });
}
$("replay-toggle").addEventListener("click", () => {
  const rp = state.replay;
  if (!rp || !state.ws || state.ws.readyState !== WebSocket.OPEN) return;
  state.ws.send(JSON.stringify({ type: "control", action: rp.paused ? "play" : "pause" }));
});
setInterval(checkFresh, FRESH_CHECK_MS);
connect();
