// pd-web page: Server-Sent Events from pd-web -> per-session buffers -> canvas drawing on
// requestAnimationFrame. Plain JS, no framework, no network access beyond this server.
// Sessions live in a Map (a name like "constructor" is a key, not a property of Object), and
// every name reaches the DOM as text (textContent, new Option), never as HTML.
"use strict";
const KEEP = 200;            // events kept per session (trail and time series)
const TRAIL = 80;            // steps of trail in the plan view
const STALE_MS = 1500;       // page-side: no event for this long -> warning
const COLORS = ["#4aa3ff", "#ff7aa8", "#7be07b", "#c59bff", "#ffd24a", "#5ee0e0", "#ff9b5e", "#b0b0b0"];
const $ = (id) => document.getElementById(id);
const S = new Map();         // session -> {ev: [...], last, tick, tickRecv, recv, lastRecv}
let selected = null, paused = false, dirty = true, lastTick = null;
const stats = {received: 0, lags: [], maxLag: 0, lastI: 0, ticks: 0, gaps: 0};

function session(name) {
  let s = S.get(name);
  if (!s) S.set(name, s = {ev: [], last: null, tick: null, tickRecv: 0, recv: 0, lastRecv: 0});
  return s;
}

function onEvent(ev) {
  if (ev.type === "hello") { S.clear(); stats.lastI = 0; dirty = true; return; }
  if (ev.type === "tick") { onTick(ev); return; }
  if (ev.i !== undefined) {  // numbered events (not the live-only frames): count the gaps
    if (stats.lastI && ev.i !== stats.lastI + 1) stats.gaps++;
    stats.lastI = ev.i;
  }
  if (ev.type === "path") { session(ev.s).path = ev; if (ev.s === selected) dirty = true; return; }
  if (ev.type === "frame") { onFrame(ev); return; }
  if (ev.type !== "pred") return;
  const now = Date.now();
  const lag = now - ev.ts;
  stats.received++;
  stats.lags.push(lag); if (stats.lags.length > 4000) stats.lags.splice(0, 2000);
  if (lag > stats.maxLag) stats.maxLag = lag;
  const fresh = !S.has(ev.s);
  const s = session(ev.s);
  // an older ownership term than the newest seen (a second owner: docs/service.md): dropped
  if (ev.term !== undefined && s.last && s.last.term !== undefined && ev.term < s.last.term) { stats.staleTerm = (stats.staleTerm || 0) + 1; return; }
  s.ev.push(ev); if (s.ev.length > KEEP) s.ev.shift();
  s.last = ev; s.recv++; s.lastRecv = now;
  if (selected === null) { selected = ev.s; }
  if (fresh) { syncPicker([]); dirty = true; }  // listed at once, not at the next tick
  if (ev.s === selected) dirty = true;
}

// a camera frame: decoded off the event loop, then drawn with its ghost by render()
function onFrame(ev) {
  const s = session(ev.s), img = new Image();
  img.onload = () => { s.frame = ev; s.frameImg = img; if (ev.s === selected) dirty = true; };
  img.src = "data:image/" + (ev.fmt === "png" ? "png" : "jpeg") + ";base64," + ev.img;
}

// the newest frame of the session, its ghost (outline at the predicted pose for the moment
// the command now sent lands, in the frame's own view), the 2-sigma ellipse and the path
function drawVideo(c, s) {
  const box = $("video-box");
  if (!s.frame) { box.hidden = true; return; }
  box.hidden = false;
  const f = s.frame, g = c.getContext("2d");
  if (c.width !== f.w || c.height !== f.h) { c.width = f.w; c.height = f.h; }
  g.drawImage(s.frameImg, 0, 0);
  const d = c.dataset;
  d.frameSeq = f.seq; d.frameTns = f.t_ns; d.frameK = f.k ?? ""; d.ageMs = f.age_ms;
  $("video-title").textContent = "camera · frame captured at step " + fmt(f.k, 1) + " · " + fmt(f.age_ms / 1000, 2) + " s old" +
    (f.ghost ? " · ghost: prediction of step " + f.ghost.k : "");
  if (f.path_px) {
    g.strokeStyle = "#c59bff"; g.lineWidth = 1.5; g.setLineDash([5, 3]); g.beginPath();
    f.path_px.forEach(([u, v], n) => (n ? g.lineTo(u, v) : g.moveTo(u, v))); g.stroke(); g.setLineDash([]);
  }
  d.pathPx = f.path_px ? JSON.stringify(f.path_px) : "";
  if (!f.ghost) { d.ghostSeq = ""; d.ghostPx = ""; return; }
  g.fillStyle = "#4aa3ff33"; g.strokeStyle = "#4aa3ff"; g.lineWidth = 1; g.beginPath();
  if (f.ghost.ell) {  // top-down view: an ellipse; perspective view: its projected polygon
    const [eu, ev, a, b, ang] = f.ghost.ell;
    g.ellipse(eu, ev, Math.max(1, a), Math.max(1, b), ang, 0, 2 * Math.PI);
  } else {
    f.ghost.ell_px.forEach(([u, v], n) => (n ? g.lineTo(u, v) : g.moveTo(u, v))); g.closePath();
  }
  g.fill(); g.stroke();
  g.strokeStyle = "#4aa3ff"; g.lineWidth = 2; g.setLineDash([4, 2]); g.beginPath();
  f.ghost.px.forEach(([u, v], n) => (n ? g.lineTo(u, v) : g.moveTo(u, v))); g.closePath(); g.stroke(); g.setLineDash([]);
  d.ghostSeq = f.ghost.seq; d.ghostK = f.ghost.k; d.ghostPx = JSON.stringify(f.ghost.px); d.ghostPose = JSON.stringify(f.ghost.pose);
  d.ghostEll = JSON.stringify(f.ghost.ell_px || f.ghost.ell);
}

function onTick(ev) {
  lastTick = ev; stats.ticks++;
  for (const name of ev.list) session(name);
  const now = Date.now();
  for (const [name, t] of Object.entries(ev.sessions)) { const s = session(name); s.tick = t; s.tickRecv = now; }
  if (selected === null && ev.list.length) selected = ev.list[0];
  syncPicker(ev.list);
  dirty = true;
}

function syncPicker(list) {
  const sel = $("session");
  const have = Array.from(sel.options).map((o) => o.value);
  const names = Array.from(new Set([...list, ...S.keys()])).sort();
  if (have.join() !== names.join()) {
    sel.replaceChildren(...names.map((n) => new Option(n, n)));
  }
  if (selected !== null) sel.value = selected;
}

// --- drawing helpers -------------------------------------------------------------------------
function fmt(v, p = 3) { return v === null || v === undefined || Number.isNaN(v) ? "–" : Number(v).toFixed(p); }
function ctx2d(c) { const g = c.getContext("2d"); g.clearRect(0, 0, c.width, c.height); return g; }
function range(vals, pad = 0.08) {
  let lo = Infinity, hi = -Infinity;
  for (const v of vals) if (v !== null && Number.isFinite(v)) { if (v < lo) lo = v; if (v > hi) hi = v; }
  if (lo === Infinity) return [0, 1];
  if (hi - lo < 1e-9) { lo -= 0.5; hi += 0.5; }
  const d = (hi - lo) * pad; return [lo - d, hi + d];
}
function arrow(g, x0, y0, x1, y1, color) {
  g.strokeStyle = g.fillStyle = color; g.lineWidth = 2;
  g.beginPath(); g.moveTo(x0, y0); g.lineTo(x1, y1); g.stroke();
  const a = Math.atan2(y1 - y0, x1 - x0);
  g.beginPath(); g.moveTo(x1, y1);
  g.lineTo(x1 - 8 * Math.cos(a - 0.4), y1 - 8 * Math.sin(a - 0.4));
  g.lineTo(x1 - 8 * Math.cos(a + 0.4), y1 - 8 * Math.sin(a + 0.4)); g.fill();
}
function label(g, text, x, y, color = "#8b98a8") { g.fillStyle = color; g.font = "12px system-ui"; g.fillText(text, x, y); }

// measured samples of the trail: one point per (sensor, step)
function measPoints(evs) {
  const seen = new Map();
  for (const ev of evs) for (const sensor in ev.meas) {
    const m = ev.meas[sensor]; if (m.k === null) continue;
    seen.set(sensor + "/" + m.k, {k: m.k, p: m.p, sensor});
  }
  return Array.from(seen.values());
}
function truthPoints(evs) {
  const seen = new Map();
  for (const ev of evs) if (ev.truth) seen.set(ev.truth.k, ev.truth);
  return Array.from(seen.values());
}

// the session's newest path, if it ends at or past the newest prediction's target (an older one
// would draw a stale future)
function pathOf(last) {
  const p = S.get(last.s)?.path;
  return p && (p.ell || last.layout === "axis") && p.k[p.k.length - 1] >= last.k ? p : null;
}
// what the plan view drew of the path, for the browser test: data-* of the canvas
function showPath(c, path) {
  const d = c.dataset;
  if (!path) { delete d.pathSeq; delete d.pathK; delete d.pathP; delete d.pathSd; return; }
  d.pathSeq = path.seq; d.pathK = JSON.stringify(path.k); d.pathP = JSON.stringify(path.p); d.pathSd = JSON.stringify(path.sd);
}

// 1-D positions (p1, p2, ...) on one horizontal axis; vertical: steps, newest at the top.
function drawAxis(c, evs, last) {
  const g = ctx2d(c), W = c.width, H = c.height, L = 50, R = 12, T = 18, B = 28;
  const pos = last.pos, names = last.names;
  const top = last.k + 2, bot = top - TRAIL;
  const recent = evs.filter((e) => e.k > bot);
  const meas = measPoints(recent), truth = truthPoints(recent);
  const vals = [];
  for (const e of recent) pos.forEach((i) => { vals.push(e.x[i] - 2 * Math.sqrt(e.var[i]), e.x[i] + 2 * Math.sqrt(e.var[i])); });
  for (const m of meas) for (const n in m.p) vals.push(m.p[n]);
  for (const t of truth) vals.push(...t.p);
  const path = pathOf(last);
  if (path) path.p.forEach((p, n) => p.forEach((v, j) => vals.push(v - 2 * path.sd[n][j], v + 2 * path.sd[n][j])));
  const [lo, hi] = range(vals);
  const X = (v) => L + (v - lo) / (hi - lo) * (W - L - R);
  const Y = (k) => T + (top - k) / (top - bot) * (H - T - B);
  // axes and grid
  g.strokeStyle = "#2c3848"; g.lineWidth = 1; g.beginPath();
  for (let i = 0; i <= 5; i++) { const v = lo + (hi - lo) * i / 5; g.moveTo(X(v), T); g.lineTo(X(v), H - B); label(g, fmt(v, 1), X(v) - 12, H - 10); }
  g.stroke();
  if (last.now !== null) {
    g.strokeStyle = "#5a6a7e"; g.setLineDash([4, 4]); g.beginPath(); g.moveTo(L, Y(last.now)); g.lineTo(W - R, Y(last.now)); g.stroke(); g.setLineDash([]);
    label(g, "now " + last.now, 2, Y(last.now) + 4);
  }
  label(g, "k " + last.k, 2, Y(last.k) + 4, "#4aa3ff");
  label(g, "position (" + pos.map((i) => names[i]).join(", ") + ")  ·  steps ↑", L, 12);
  // truth trail
  pos.forEach((i, j) => {
    g.strokeStyle = "#e8e8e8"; g.lineWidth = 1; g.beginPath();
    truth.forEach((t, n) => { const x = X(t.p[j]), y = Y(t.k); n ? g.lineTo(x, y) : g.moveTo(x, y); }); g.stroke();
  });
  // predicted path (newest measured step -> target) with its 2-sigma band
  if (path) pos.forEach((i, j) => {
    const col = COLORS[j % COLORS.length];
    g.fillStyle = col + "30"; g.beginPath();
    path.k.forEach((k, n) => { const x = X(path.p[n][j] - 2 * path.sd[n][j]); n ? g.lineTo(x, Y(k)) : g.moveTo(x, Y(k)); });
    for (let n = path.k.length - 1; n >= 0; n--) g.lineTo(X(path.p[n][j] + 2 * path.sd[n][j]), Y(path.k[n]));
    g.closePath(); g.fill();
    g.strokeStyle = col; g.lineWidth = 1.5; g.setLineDash([6, 3]); g.beginPath();
    path.k.forEach((k, n) => { n ? g.lineTo(X(path.p[n][j]), Y(k)) : g.moveTo(X(path.p[n][j]), Y(k)); }); g.stroke(); g.setLineDash([]);
  });
  showPath(c, path);
  // predicted trail + 2-sigma ellipse of the newest
  pos.forEach((i, j) => {
    const col = COLORS[j % COLORS.length];
    g.strokeStyle = col; g.lineWidth = 2; g.beginPath();
    recent.forEach((e, n) => { const x = X(e.x[i]), y = Y(e.k); n ? g.lineTo(x, y) : g.moveTo(x, y); }); g.stroke();
    const sd = Math.sqrt(last.var[i]), cx = X(last.x[i]), cy = Y(last.k);
    g.fillStyle = col + "55"; g.strokeStyle = col; g.beginPath();
    g.ellipse(cx, cy, Math.max(2, X(last.x[i] + 2 * sd) - cx), 7, 0, 0, 2 * Math.PI); g.fill(); g.stroke();
    label(g, names[i], cx + 4, cy - 9, col);
  });
  // measured samples (delayed): dots at their sample step
  g.fillStyle = "#ffb020";
  for (const m of meas) for (const n in m.p) { g.beginPath(); g.arc(X(m.p[n]), Y(m.k), 3, 0, 2 * Math.PI); g.fill(); }
  // command: arrow at the first position's prediction, length ~ u[0]
  if (last.cmd && last.cmd.u.length) {
    const u = last.cmd.u[0], cx = X(last.x[pos[0]]), cy = Y(last.k) - 16;
    if (u) arrow(g, cx, cy, cx + Math.max(-60, Math.min(60, 60 * u)), cy, "#4caf50");
    label(g, "u " + fmt(u, 2), cx + 6, cy - 6, "#4caf50");
  }
}

// planar robot: x, y with the 2-sigma ellipse of (x, y).
function drawPlane(c, evs, last) {
  const g = ctx2d(c), W = c.width, H = c.height, M = 30;
  const [ix, iy] = last.pos;
  const recent = evs.slice(-TRAIL), meas = measPoints(recent), truth = truthPoints(recent);
  const xs = [], ys = [];
  for (const e of recent) { xs.push(e.x[ix]); ys.push(e.x[iy]); }
  for (const t of truth) { xs.push(t.p[0]); ys.push(t.p[1]); }
  const nx = last.names[ix], ny = last.names[iy];
  for (const m of meas) { if (Object.hasOwn(m.p, nx)) xs.push(m.p[nx]); if (Object.hasOwn(m.p, ny)) ys.push(m.p[ny]); }
  if (last.ell) { xs.push(last.ell[0] - last.ell[2], last.ell[0] + last.ell[2]); ys.push(last.ell[1] - last.ell[2], last.ell[1] + last.ell[2]); }
  const path = pathOf(last);
  if (path) for (const [ex, ey, a] of path.ell) { xs.push(ex - a, ex + a); ys.push(ey - a, ey + a); }
  let [x0, x1] = range(xs), [y0, y1] = range(ys);
  const s = Math.min((W - 2 * M) / (x1 - x0), (H - 2 * M) / (y1 - y0));
  const cxm = (x0 + x1) / 2, cym = (y0 + y1) / 2;
  const X = (v) => W / 2 + (v - cxm) * s, Y = (v) => H / 2 - (v - cym) * s;
  label(g, nx + " → · " + ny + " ↑ (scale " + fmt(1 / s * 50, 2) + " per 50 px)", 6, 14);
  const line = (pts, col, w) => { g.strokeStyle = col; g.lineWidth = w; g.beginPath(); pts.forEach((p, n) => n ? g.lineTo(X(p[0]), Y(p[1])) : g.moveTo(X(p[0]), Y(p[1]))); g.stroke(); };
  line(truth.map((t) => t.p), "#e8e8e8", 1);
  line(recent.map((e) => [e.x[ix], e.x[iy]]), "#4aa3ff", 2);
  // predicted path with its 2-sigma band: the union of each step's 2-sigma ellipse
  if (path) {
    g.fillStyle = "#c59bff22";
    for (const [ex, ey, a, b, ang] of path.ell) { g.beginPath(); g.ellipse(X(ex), Y(ey), Math.max(1, a * s), Math.max(1, b * s), -ang, 0, 2 * Math.PI); g.fill(); }
    g.setLineDash([6, 3]); line(path.p, "#c59bff", 1.5); g.setLineDash([]);
  }
  showPath(c, path);
  g.fillStyle = "#ffb020";
  for (const m of meas) if (Object.hasOwn(m.p, nx) && Object.hasOwn(m.p, ny)) { g.beginPath(); g.arc(X(m.p[nx]), Y(m.p[ny]), 3, 0, 2 * Math.PI); g.fill(); }
  if (last.ell) {
    const [ex, ey, a, b, ang] = last.ell;
    g.fillStyle = "#4aa3ff44"; g.strokeStyle = "#4aa3ff"; g.beginPath();
    g.ellipse(X(ex), Y(ey), Math.max(2, a * s), Math.max(2, b * s), -ang, 0, 2 * Math.PI); g.fill(); g.stroke();
  }
  if (last.cmd && last.cmd.u.length >= 2) {
    const [u0, u1] = last.cmd.u, n = Math.hypot(u0, u1) || 1, L = Math.min(60, 30 * n);
    arrow(g, X(last.x[ix]), Y(last.x[iy]), X(last.x[ix]) + L * u0 / n, Y(last.x[iy]) - L * u1 / n, "#4caf50");
  }
}

// time series: [{name, color, pts: [[k, v]]}] on a shared step axis
function chart(c, series, log) {
  const g = ctx2d(c), W = c.width, H = c.height, L = 46, R = 8, T = 8, B = 18;
  const tf = (v) => (log ? (v > 0 ? Math.log10(v) : null) : v);
  const ks = [], vs = [];
  for (const s of series) for (const [k, v] of s.pts) { ks.push(k); vs.push(tf(v)); }
  if (!ks.length) { label(g, "no data", W / 2 - 20, H / 2); return; }
  const [k0, k1] = range(ks, 0), [v0, v1] = range(vs);
  const X = (k) => L + (k - k0) / (k1 - k0 || 1) * (W - L - R), Y = (v) => T + (v1 - v) / (v1 - v0) * (H - T - B);
  g.strokeStyle = "#2c3848"; g.beginPath();
  for (let i = 0; i <= 3; i++) { const v = v0 + (v1 - v0) * i / 3; g.moveTo(L, Y(v)); g.lineTo(W - R, Y(v)); label(g, log ? "1e" + fmt(v, 1) : fmt(v, 2), 2, Y(v) + 4); }
  g.stroke(); label(g, "k " + k0, L, H - 4); label(g, "k " + k1, W - R - 50, H - 4);
  series.forEach((s, j) => {
    g.strokeStyle = s.color; g.lineWidth = 1.5; g.beginPath(); let started = false;
    for (const [k, v] of s.pts) { const t = tf(v); if (t === null) continue; started ? g.lineTo(X(k), Y(t)) : g.moveTo(X(k), Y(t)); started = true; }
    g.stroke(); label(g, s.name, L + 6 + j * 60, T + 12, s.color);
  });
}

function drawSeries(evs, last) {
  const names = last.names, pos = last.pos;
  const errs = new Map(); for (const e of evs) if (e.err) errs.set(e.err.k, e.err.e);
  const errK = Array.from(errs.keys()).sort((a, b) => a - b);
  chart($("ts-err"), pos.map((i, j) => ({name: names[i], color: COLORS[j % COLORS.length],
    pts: errK.map((k) => [k, errs.get(k)[i]])})), false);
  chart($("ts-var"), names.map((n, i) => ({name: n, color: COLORS[i % COLORS.length], pts: evs.map((e) => [e.k, e.var[i]])})), true);
  const sensors = Object.keys(last.delay_ms);
  chart($("ts-delay"), sensors.map((s, j) => ({name: s, color: COLORS[(j + 4) % COLORS.length],
    pts: evs.filter((e) => Object.hasOwn(e.delay_ms, s)).map((e) => [e.k, e.delay_ms[s]])})), false);
  chart($("ts-lat"), [{name: "latency", color: COLORS[2], pts: evs.map((e) => [e.k, e.lat_ms])}], false);
}

// the server's warnings ([what, seconds since] at its tick) aged by the time since that tick:
// they go on counting after the stream is lost
function warnings(name) {
  const s = S.get(name); if (!s) return [];
  const now = Date.now(), since = (now - s.tickRecv) / 1000;
  const out = s.tick ? s.tick.warn.map(([what, age]) => [what, age + since]) : [];
  if (s.lastRecv && now - s.lastRecv > STALE_MS && !out.some(([what]) => what === "no prediction"))
    out.unshift(["no prediction", (now - s.lastRecv) / 1000]);
  return out.map(([what, age]) => what + " for " + age.toFixed(1) + " s");
}

function renderWarnings() {
  const w = selected ? warnings(selected) : [];
  const box = $("warn");
  box.hidden = w.length === 0; box.textContent = w.length ? "⚠ " + selected + ": " + w.join(" · ") : "";
  box.dataset.warn = w.join("|");
}

// a table row of text cells: [text, attributes] pairs, or texts
function row(cells, data, cls) {
  const tr = document.createElement("tr");
  if (cls) tr.className = cls;
  for (const [k, v] of Object.entries(data)) tr.dataset[k] = v;
  for (const c of cells) {
    const td = document.createElement("td");
    if (Array.isArray(c)) { td.textContent = c[0]; td.className = c[1]; } else td.textContent = c;
    tr.append(td);
  }
  return tr;
}

function render() {
  const s = selected !== null ? S.get(selected) : undefined;
  renderOverview();
  if (!s || !s.last) return;
  const last = s.last, evs = s.ev;
  $("plan-title").textContent = "plan view · " + selected + (last.layout === "axis" ? " (positions on one axis)" : "");
  (last.layout === "plane" ? drawPlane : drawAxis)($("plan"), evs, last);
  drawVideo($("video"), s);
  drawSeries(evs, last);
  // numeric readout (also read by the browser test through its data-* attributes)
  const tb = $("values"); const rows = [];
  last.pos.forEach((i, j) => {
    const n = last.names[i], sd = Math.sqrt(last.var[i]);
    let mv = null, age = null;
    for (const sensor in last.meas) { const m = last.meas[sensor]; if (Object.hasOwn(m.p, n) && (mv === null || m.k > mv.k)) { mv = {v: m.p[n], k: m.k}; age = m.age_ms; } }
    const tv = last.truth ? last.truth.p[j] : null;
    rows.push(row([n, fmt(last.x[i]), "±" + fmt(2 * sd), mv ? fmt(mv.v) : "–", age === null ? "–" : fmt(age / 1000, 2) + " s", fmt(tv)],
      {name: n, x: last.x[i], sd: sd, meas: mv ? mv.v : "", ageMs: age === null ? "" : age, truth: tv === null ? "" : tv}));
  });
  tb.replaceChildren(...rows);
  tb.dataset.session = selected; tb.dataset.k = last.k; tb.dataset.seq = last.seq; tb.dataset.term = last.term ?? "";
  $("info").textContent = `target step ${last.k} · now ${last.now ?? "?"} · lead ${last.lead ?? "?"} · latency ${fmt(last.lat_ms, 1)} ms` +
    (last.st ? ` · ${last.st} predictions of an older owner dropped` : "") +
    (last.err ? ` · error at ${last.err.k}: ` + last.pos.map((i) => last.names[i] + " " + fmt(last.err.e[i])).join(", ") : "") +
    (last.cmd ? ` · command u(${last.cmd.k}) = [${last.cmd.u.map((v) => fmt(v, 2)).join(", ")}]` : "");
  $("counters").replaceChildren(...Object.entries(last.c).map(([k, v]) => {
    const d = document.createElement("div"), b = document.createElement("b");
    d.dataset.counter = k; b.textContent = v; d.append(b, k); return d;
  }));
}

function renderOverview() {
  const rows = [];
  for (const name of Array.from(S.keys()).sort()) {
    const s = S.get(name), c = s.last ? s.last.c : {}, w = warnings(name);
    rows.push(row([name, s.recv, ...["accepted", "late", "future", "refused"].map((k) => c[k] ?? "–"),
      [w.length ? "⚠ " + w.length : "ok", w.length ? "bad" : ""]], {session: name}, name === selected ? "sel" : ""));
  }
  $("overview").replaceChildren(...rows);
}

function publishStats() {
  const l = stats.lags.slice().sort((a, b) => a - b);
  const q = (p) => (l.length ? l[Math.min(l.length - 1, Math.floor(p * l.length))] : 0);
  const d = $("stats").dataset;
  d.received = stats.received; d.gaps = stats.gaps; d.lastI = stats.lastI; d.ticks = stats.ticks;
  d.lagP50 = q(0.5).toFixed(1); d.lagP95 = q(0.95).toFixed(1); d.lagMax = stats.maxLag.toFixed(1);
}

function frame() {
  if (dirty) { dirty = false; renderWarnings(); if (!paused) render(); }  // paused: warnings still age
  publishStats();
  $("clock").textContent = new Date().toLocaleTimeString();
  requestAnimationFrame(frame);
}

// EventSource retries a lost stream by itself, but not a refused one (HTTP 503 at pd-web's
// page cap, 403 for a Host it does not serve): then the reason is fetched and shown.
function connect() {
  const es = new EventSource("events");
  es.onopen = () => { $("conn").textContent = "live"; $("conn").className = "conn live"; };
  es.onmessage = (m) => onEvent(JSON.parse(m.data));
  es.onerror = () => {
    $("conn").className = "conn lost"; dirty = true;
    if (es.readyState !== EventSource.CLOSED) { $("conn").textContent = "stream lost: showing the last state (retrying)"; return; }
    $("conn").textContent = "stream refused: showing the last state (retrying in 10 s)";
    fetch("events").then((r) => (r.ok ? r.body.cancel().then(() => "") : r.text())).catch(() => "")
      .then((why) => { if (why) $("conn").textContent = "stream refused: " + why.trim() + " (retrying in 10 s)"; });
    setTimeout(connect, 10000);
  };
}

$("session").onchange = (e) => { selected = e.target.value; dirty = true; render(); };
$("overview").onclick = (e) => { const tr = e.target.closest("tr"); if (tr) { selected = tr.dataset.session; syncPicker([]); dirty = true; render(); } };
$("pause").onclick = () => {
  paused = !paused; $("pause").textContent = paused ? "resume" : "pause";
  $("pause").className = paused ? "paused" : ""; dirty = true;
};
setInterval(() => { dirty = true; renderWarnings(); }, 500);  // warnings age even when no event arrives
connect();
requestAnimationFrame(frame);
