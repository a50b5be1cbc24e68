// tiltlab dashboard: live readings over /ws/readings drawn with uPlot, bench and device status,
// calibration jobs followed over /ws/jobs/{id}, levelling, stop, and records with their residual maps.
"use strict";

const $ = (id) => document.getElementById(id);
const TOKEN_KEY = "tiltlab-token";
const BACKOFF_MIN_MS = 500;
const BACKOFF_MAX_MS = 15000;
const STATUS_POLL_MS = 2000;
const MAX_RATE_HZ = 50;
const MAX_WINDOW_S = 3600;

// ------------------------------------------------------------------ token

const fragment = new URLSearchParams(location.hash.slice(1));
if (fragment.get("token")) {
  sessionStorage.setItem(TOKEN_KEY, fragment.get("token"));
  history.replaceState(null, "", location.pathname + location.search);
}
const token = sessionStorage.getItem(TOKEN_KEY);

function showAuth(title, detail) {
  $("auth-title").textContent = title;
  $("auth-detail").textContent = detail || "";
  $("auth").hidden = false;
  document.body.classList.add("locked");
  stopEverything();
}

// ------------------------------------------------------------------ formatting (every number with its unit)

const isNum = (v) => typeof v === "number" && Number.isFinite(v);
const deg = (v, d = 4) => (isNum(v) ? `${v.toFixed(d)}°` : "—");
const arcsec = (vDeg, d = 1) => (isNum(vDeg) ? `${(vDeg * 3600).toFixed(d)}″` : "—");
const degArc = (v) => (isNum(v) ? `${v.toFixed(5)}° (${(v * 3600).toFixed(1)}″)` : "—");
// GUM 7.2.6: an expanded uncertainty to two significant digits, the value to the same decimal place
function uDecimals(u) { return isNum(u) && u > 0 ? Math.max(0, 1 - Math.floor(Math.log10(u))) : 4; }
function gumDeg(v, u) {
  if (!isNum(v)) return "—";
  if (!isNum(u) || !(u > 0)) return `${v.toFixed(4)}°`;
  const d = uDecimals(u);
  return `${v.toFixed(d)}° ± ${u.toFixed(d)}°`;
}
const kText = (k) => (isNum(k) ? k.toPrecision(3) : "—");  // a coverage factor to three digits
const utcTime = (t) => (t ? new Date(t).toISOString().slice(11, 23) + " UTC" : "—");
const utcDate = (t) => (t ? new Date(t).toISOString().slice(0, 19).replace("T", " ") : "—");
const ageText = (t, zone = true) => {
  if (!t) return "never";
  const s = (Date.now() - new Date(t).getTime()) / 1000;
  return `${zone ? utcTime(t) : utcTime(t).replace(" UTC", "")} (${Math.max(0, s).toFixed(1)} s ago)`;
};

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "onclick") e.addEventListener("click", v);
    else if (v !== null && v !== undefined) e.setAttribute(k, v);
  }
  for (const c of children) e.append(c instanceof Node ? c : document.createTextNode(String(c)));
  return e;
}

function svgEl(tag, attrs = {}, text) {
  const e = document.createElementNS("http://www.w3.org/2000/svg", tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
}

// ------------------------------------------------------------------ HTTP

class ApiError extends Error {
  constructor(status, detail) { super(detail); this.status = status; }
}

async function api(method, path, body) {
  const headers = { Accept: "application/json", Authorization: `Bearer ${token}` };
  if (body !== undefined) headers["Content-Type"] = "application/json";
  let r;
  try {
    r = await fetch(path, { method, headers, cache: "no-store", body: body === undefined ? undefined : JSON.stringify(body) });
  } catch (_) {
    throw new ApiError(0, `no answer from the service at ${path}`);
  }
  if (!r.ok) {
    let detail = r.statusText;
    try { const p = await r.json(); detail = p.detail || p.title || detail; } catch (_) { /* not problem+json */ }
    if (r.status === 401) showAuth("The token was not accepted", `${path} answered 401: ${detail}`);
    if (r.status === 403 && method === "GET") showAuth("The token lacks a scope this page needs", `${path} answered 403: ${detail}`);
    throw new ApiError(r.status, `${method} ${path} answered HTTP ${r.status}: ${detail}`);
  }
  const type = r.headers.get("content-type") || "";
  return type.includes("json") ? r.json() : r.blob();
}

function showProblem(text) { $("banner").textContent = text; $("banner").hidden = !text; }

// The token travels as the subprotocol bearer.<token>, never in the URL (URLs end up in logs).
// Text a subprotocol cannot carry goes in the query, so the daemon can say why it was refused.
const SUBPROTOCOL_SAFE = /^[A-Za-z0-9._~-]+$/;

function wsUrl(path, params) {
  const q = new URLSearchParams(SUBPROTOCOL_SAFE.test(token || "") ? params : { ...params, token });
  return `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}${path}?${q}`;
}

function wsProtocols() { return SUBPROTOCOL_SAFE.test(token || "") ? [`bearer.${token}`] : []; }

// A WebSocket that reconnects with exponential back-off and says when it is lost.
class Stream {
  constructor(name, urlFn, { onMessage, onState, shouldReconnect = () => true }) {
    Object.assign(this, { name, urlFn, onMessage, onState, shouldReconnect });
    this.attempt = 0; this.ws = null; this.timer = null; this.closed = false;
  }
  open() {
    this.closed = false;
    clearTimeout(this.timer);
    const ws = new WebSocket(this.urlFn(), wsProtocols());
    this.ws = ws;
    ws.onopen = () => { this.attempt = 0; };
    ws.onmessage = (ev) => {
      if (ws !== this.ws) return;
      this.attempt = 0;
      this.onState("open");
      this.onMessage(JSON.parse(ev.data));
    };
    ws.onclose = (ev) => {
      if (ws !== this.ws || this.closed) return;
      this.ws = null;
      if (ev.code === 1008) {  // policy: the token was refused
        showAuth("The token was not accepted", `${this.name} stream closed: ${ev.reason || "token refused"}`);
        return;
      }
      if (!this.shouldReconnect(ev)) { this.onState("ended", ev); return; }
      const delay = Math.min(BACKOFF_MAX_MS, BACKOFF_MIN_MS * 2 ** this.attempt);
      this.attempt += 1;
      this.onState("lost", { code: ev.code, reason: ev.reason, delay, attempt: this.attempt });
      this.timer = setTimeout(() => this.open(), delay);
    };
  }
  close() {
    this.closed = true;
    clearTimeout(this.timer);
    if (this.ws) { const ws = this.ws; this.ws = null; ws.close(1000); }
  }
}

// ------------------------------------------------------------------ state

const state = {
  bench: null, benches: [], readings: null, job: null, jobStream: null, jobPoints: new Map(), jobEnded: false,
  moving: false, actionInFlight: 0, records: [], selectedRecord: null, statusTimer: null,
};

function stopEverything() {
  if (state.readings) state.readings.close();
  if (state.jobStream) state.jobStream.close();
  clearTimeout(state.statusTimer);
}

// ------------------------------------------------------------------ ring buffer of readings

// Columns in a linear buffer of twice the capacity: appends are O(1) amortised and the newest
// `capacity` values are always one contiguous subarray (what uPlot draws without copying).
const SERIES = ["t", "tx", "ty", "txlo", "txhi", "tylo", "tyhi", "mx", "my", "rx", "ry"];
class Ring {
  constructor(capacity) {
    this.capacity = capacity; this.len = 0;
    this.cols = Object.fromEntries(SERIES.map((k) => [k, new Float64Array(2 * capacity)]));
  }
  get lastT() { return this.len ? this.cols.t[this.len - 1] : -Infinity; }
  push(row) {
    if (this.len === 2 * this.capacity) {
      for (const k of SERIES) this.cols[k].copyWithin(0, this.capacity, 2 * this.capacity);
      this.len = this.capacity;
    }
    for (const k of SERIES) this.cols[k][this.len] = row[k];
    this.len += 1;
  }
  clear() { this.len = 0; }
  // index of the first value with t >= t0
  lowerBound(t0) {
    let lo = Math.max(0, this.len - this.capacity), hi = this.len;
    while (lo < hi) { const mid = (lo + hi) >> 1; if (this.cols.t[mid] < t0) lo = mid + 1; else hi = mid; }
    return lo;
  }
  view(t0) {
    const i0 = this.lowerBound(t0);
    return Object.fromEntries(SERIES.map((k) => [k, this.cols[k].subarray(i0, this.len)]));
  }
  get size() { return Math.min(this.len, this.capacity); }
}

const ring = new Ring(Math.ceil(MAX_WINDOW_S * MAX_RATE_HZ * 1.1));
const live = { received: 0, dropped: 0, draws: 0, dirty: false, latest: null, windowS: 60, snapshots: 0, snapshotT: null };
window.tiltlab = { ring, live, state };  // for inspection from the browser's console (and the browser tests)

function toRow(m) {
  const t = new Date(m.time_utc).getTime() / 1000;
  const tt = m.table_tilt, raw = m.raw || {};
  const meas = raw.measurement_sensor || {}, ref = raw.reference_sensor || {};
  const v = (x) => (isNum(x) ? x : NaN);
  const ux = tt && isNum(tt.u_x_deg) ? tt.u_x_deg : NaN, uy = tt && isNum(tt.u_y_deg) ? tt.u_y_deg : NaN;
  const tx = tt ? v(tt.x_deg) : NaN, ty = tt ? v(tt.y_deg) : NaN;
  return { t, tx, ty, txlo: tx - ux, txhi: tx + ux, tylo: ty - uy, tyhi: ty + uy,
    mx: v(meas.x_deg), my: v(meas.y_deg), rx: v(ref.x_deg), ry: v(ref.y_deg) };
}

function addReading(m) {
  const row = toRow(m);
  if (!(row.t > ring.lastT)) return false;  // already have it (a reconnect's history overlaps)
  ring.push(row);
  live.latest = m;
  live.dirty = true;
  return true;
}

function onReadingMessage(m) {
  if (m.type === "snapshot") {
    // the history fills the gap since the last reading we hold (oldest first); then the snapshot itself
    for (const h of m.history || []) addReading(h);
    addReading(m);
    live.snapshots += 1;
    live.snapshotT = ring.lastT;
    live.calibration = m.calibration;
    $("stream-state").textContent = `${m.bench}, ${isNum(m.rate_hz) ? m.rate_hz.toFixed(1) : "?"} Hz`;
  } else if (m.type === "reading") {
    live.received += 1;
    // each reading names the record that corrected it: an activation shows with the next reading
    if (m.calibration !== undefined) live.calibration = m.calibration;
    addReading(m);
  } else if (m.type === "dropped") {
    live.dropped += m.count || 0;
  }
}

// ------------------------------------------------------------------ charts (uPlot), redrawn once per animation frame

let tiltChart = null, rawChart = null;

function chartSize(div) {
  const w = Math.max(260, div.clientWidth || 600);
  return { width: w, height: w < 600 ? 180 : 220 };
}

function axisDeg() {
  return { label: "°", size: 70, values: (u, vals) => vals.map((v) => (v === null ? "" : `${+v.toPrecision(6)}°`)) };
}

// the page speaks UTC: the time axis says UTC time of day, 24 h, never the browser's zone
function utcClock(t, ms = 0) {
  const s = new Date(t * 1e3).toISOString();
  return ms ? s.slice(11, 20 + ms) : s.slice(11, 19);
}
function axisUtc() {
  return { label: "time (UTC)", labelSize: 20, values: (u, splits, ax, space, incr) => splits.map((t) => (t === null ? "" : utcClock(t, incr < 1 ? 1 : 0))) };
}

function makeCharts() {
  if (typeof uPlot === "undefined") { showProblem("the chart library did not load (/web/vendor/uplot)"); return; }
  const x = { label: "time (UTC)", value: (u, t) => (isNum(t) ? utcClock(t, 3) : "—") };
  const common = {
    scales: { x: { time: true, range: () => [xRange[0], xRange[1]] }, y: { auto: true, range: (u) => yRange(u) } },
    tzDate: (t) => uPlot.tzDate(new Date(t * 1e3), "Etc/UTC"),  // ticks on whole UTC seconds and minutes
    axes: [axisUtc(), axisDeg()], legend: { live: true }, cursor: { drag: { x: false, y: false } },
  };
  // a bound of the band is drawn by no line and filled by nothing of its own: uPlot fills a series'
  // own `fill` down to zero; the band between reading − U and reading + U is filled by `bands` alone
  const band = (c) => ({ stroke: c, width: 0, points: { show: false }, legend: false });
  tiltChart = new uPlot({
    ...chartSize($("chart-tilt")), ...common,
    series: [x, { label: "X", stroke: "#1f5fbf", width: 1.5, points: { show: false } },
      { label: "Y", stroke: "#c0392b", width: 1.5, points: { show: false } },
      { label: "X − U", ...band("#1f5fbf") }, { label: "X + U", ...band("#1f5fbf") },
      { label: "Y − U", ...band("#c0392b") }, { label: "Y + U", ...band("#c0392b") }],
    bands: [{ series: [4, 3], fill: "#1f5fbf30" }, { series: [6, 5], fill: "#c0392b30" }],
  }, [[], [], [], [], [], [], []], $("chart-tilt"));
  rawChart = new uPlot({
    ...chartSize($("chart-raw")), ...common,
    series: [x, { label: "meas X", stroke: "#1f5fbf", width: 1.2, points: { show: false } },
      { label: "meas Y", stroke: "#c0392b", width: 1.2, points: { show: false } },
      { label: "ref X", stroke: "#1f5fbf", dash: [4, 3], width: 1.2, points: { show: false } },
      { label: "ref Y", stroke: "#c0392b", dash: [4, 3], width: 1.2, points: { show: false } }],
  }, [[], [], [], [], []], $("chart-raw"));
  window.tiltlab.charts = { tilt: tiltChart, raw: rawChart };
  window.addEventListener("resize", () => {
    tiltChart.setSize(chartSize($("chart-tilt")));
    rawChart.setSize(chartSize($("chart-raw")));
  });
}

let xRange = [0, 1];

// The y range over the finite values of a chart's series (NaN marks a missing value in the typed arrays).
function yRange(u) {
  let lo = Infinity, hi = -Infinity;
  for (let i = 1; i < u.data.length; i++) {
    const d = u.data[i];
    for (let j = 0; j < d.length; j++) { const v = d[j]; if (v < lo) lo = v; if (v > hi) hi = v; }
  }
  if (!(lo <= hi)) return [-1, 1];
  const pad = Math.max((hi - lo) * 0.08, 1e-4);
  return [lo - pad, hi + pad];
}

function frame() {
  if (live.dirty && tiltChart && !$("view-live").hidden) {
    live.dirty = false;
    const end = ring.lastT;
    xRange = [end - live.windowS, end];
    const v = ring.view(end - live.windowS);
    const hasTilt = v.tx.some(Number.isFinite);
    // the corrected tilt from its first value in the window on (before a record is active there is none)
    let i0 = 0;
    while (i0 < v.tx.length && !Number.isFinite(v.tx[i0])) i0++;
    const s = (a) => a.subarray(i0);
    tiltChart.setData([s(v.t), s(v.tx), s(v.ty), s(v.txlo), s(v.txhi), s(v.tylo), s(v.tyhi)]);
    rawChart.setData([v.t, v.mx, v.my, v.rx, v.ry]);
    live.draws += 1;
    $("chart-tilt").dataset.points = String(v.t.length);
    $("chart-raw").dataset.points = String(v.t.length);
    $("tilt-note").textContent = hasTilt ? "" : "no corrected table tilt in this window (no active calibration record, or the sensor is silent)";
    showLatest(live.latest);
  }
  $("n-readings").textContent = String(live.received);
  $("n-buffer").textContent = String(ring.size);
  $("n-dropped").textContent = String(live.dropped);
  $("n-draws").textContent = String(live.draws);
  requestAnimationFrame(frame);
}

function showLatest(m) {
  if (!m) return;
  const raw = m.raw || {}, meas = raw.measurement_sensor || {}, ref = raw.reference_sensor || {}, st = m.stage || {};
  $("ref_x").textContent = deg(ref.x_deg); $("ref_y").textContent = deg(ref.y_deg);
  $("meas_x").textContent = deg(meas.x_deg); $("meas_y").textContent = deg(meas.y_deg);
  $("stage_x").textContent = deg(st.x_deg); $("stage_y").textContent = deg(st.y_deg);
  $("stage_moving").textContent = st.moving ? "moving" : "standing";
  $("temp_c").textContent = isNum(m.temp_c) ? `${m.temp_c.toFixed(2)} °C` : "—";
  $("updated").textContent = `at ${utcTime(m.time_utc)}`;
  const tt = m.table_tilt;
  $("tilt_x").textContent = tt ? gumDeg(tt.x_deg, tt.u_x_deg) : "—";
  $("tilt_y").textContent = tt ? gumDeg(tt.y_deg, tt.u_y_deg) : "—";
  const c = live.calibration;
  const ks = tt ? `k = ${kText(tt.k)} in X, k_y = ${kText(tt.k_y)} in Y` : "";
  const p = tt && isNum(tt.coverage_probability) ? ` (${+(tt.coverage_probability * 100).toPrecision(3)} % coverage)` : "";
  $("calibration-note").textContent = tt ? `uncertainty expanded with ${ks}${p}${c ? `; record ${c.record_id} v${c.version} (${c.method})` : ""}`
    : "no corrected tilt: no active calibration record, or the measurement sensor is silent";
  setMoving(!!st.moving, "stream");
}

function openReadings() {
  if (state.readings) state.readings.close();
  ring.clear();
  live.latest = null; live.dirty = true;
  state.readings = new Stream("readings", () => wsUrl("/ws/readings", {
    bench: state.bench, rate_hz: $("rate").value,
    // ask for the window, or for the time since the last reading we hold when that is shorter (the gap)
    history_s: String(Math.ceil(ring.len ? Math.min(live.windowS, Date.now() / 1000 - ring.lastT + 2) : live.windowS)),
  }), {
    onMessage: onReadingMessage,
    onState: (s, info) => {
      const b = $("stream-banner");
      if (s === "open") { b.hidden = true; document.body.classList.remove("stale"); return; }
      if (s === "lost") {
        b.textContent = `Live stream lost (${info.code}${info.reason ? `: ${info.reason}` : ""}); reconnecting in ${(info.delay / 1000).toFixed(1)} s (attempt ${info.attempt}).`;
        b.hidden = false;
        document.body.classList.add("stale");
        $("stream-state").textContent = "disconnected";
      }
    },
  });
  state.readings.open();
}

// ------------------------------------------------------------------ status: benches, devices, active records

const ROLE_OF_KIND = { stage: "measurement_sensor", scale: "adc_sensor", rotation: "triaxial_sensor", turntable: "turntable_sensor" };

// A bench in the selector: its name, and in a fleet (benches on more than one node) the node it hangs off
// and whether that node is offline. A daemon alone names only its benches.
function benchLabel(x, benches) {
  if (!x.node || new Set(benches.map((y) => y.node)).size < 2) return x.name;
  return `${x.name} · ${x.node}${x.online === false ? " (offline)" : ""}`;
}

async function loadBenches() {
  const b = await api("GET", "/benches");
  state.benches = b.benches;
  const sel = $("bench-select");
  if (!sel.options.length) {
    for (const x of b.benches) sel.append(el("option", { value: x.name }, benchLabel(x, b.benches)));
    const first = b.benches.find((x) => x.kind === "stage") || b.benches[0];
    state.bench = first ? first.name : null;
    sel.value = state.bench;
  }
  return b;
}

async function refreshStatus() {
  clearTimeout(state.statusTimer);
  try {
    // the bench list first: in a fleet another node's bench may not answer, and the list says why
    const devicesAsked = api("GET", `/devices?bench=${encodeURIComponent(state.bench)}`);
    const recordsAsked = api("GET", `/records?bench=${encodeURIComponent(state.bench)}`);
    devicesAsked.catch(() => {});
    recordsAsked.catch(() => {});
    const b = await api("GET", "/benches");
    state.benches = b.benches;
    for (const opt of $("bench-select").options) {  // a fleet's benches come and go with their nodes
      const x = b.benches.find((y) => y.name === opt.value);
      if (x) opt.textContent = benchLabel(x, b.benches);
    }
    const me = b.benches.find((x) => x.name === state.bench);
    $("bench-state").textContent = me ? `${me.state}${me.held_by ? `: ${me.held_by}` : ""}` : "?";
    $("bench-state").className = `pill ${me ? me.state : ""}`;
    setMoving(!!(me && me.held_by), "bench");
    const tb = $("benches").tBodies[0];
    tb.replaceChildren(...b.benches.map((x) => el("tr", { "data-bench": x.name }, el("td", {}, x.name),
      el("td", {}, x.node ? `${x.node}${x.online === false ? " (offline)" : ""}` : "—"), el("td", {}, x.kind),
      el("td", { class: `st-${x.state}` }, x.state), el("td", {}, x.held_by || "—"),
      el("td", {}, x.simulated ? `${x.simulated.scenario || "yes"}, ${x.simulated.speed}× speed` : "no"))));
    const [d, r] = await Promise.all([devicesAsked, recordsAsked]);
    const active = {};
    for (const rec of r.records) if (rec.active) active[ROLE_OF_KIND[rec.kind]] = rec;
    const td = $("devices").tBodies[0];
    td.replaceChildren(...d.devices.map((x) => {
      const c = x.counters, a = active[x.role];
      return el("tr", { "data-role": x.role }, el("td", {}, x.role.replace(/_/g, " ")), el("td", { class: "port" }, x.port),
        el("td", {}, x.protocol), el("td", { class: `st-${x.state}` }, x.state), el("td", {}, ageText(x.last_frame_utc, false)),
        el("td", {}, `${c.frames}`), el("td", {}, `${c.bad_checksum} / ${c.resyncs} / ${c.timeouts} / ${c.reconnects}`),
        el("td", { class: "wrap" }, x.identity ? `${x.identity.model} s/n ${x.identity.serial}${x.identity.firmware ? ` fw ${x.identity.firmware}` : ""}` : "—"),
        el("td", { class: "wrap" }, a ? `record ${a.id} v${a.version} (${a.method})` : "none"), el("td", { class: "wrap" }, x.error || "—"));
    }));
    state.devices = d.devices;
    $("devices-updated").textContent = `at ${utcTime(new Date().toISOString())}`;
    state.records = r.records;
    if (!$("view-records").hidden) drawRecords();
    showProblem("");
  } catch (err) {
    if (err.status !== 401 && err.status !== 403) showProblem(err.message);
  }
  if ($("auth").hidden) state.statusTimer = setTimeout(refreshStatus, STATUS_POLL_MS);
}

// ------------------------------------------------------------------ the stop button: visible while anything moves

const movingBy = {};
function setMoving(on, source) {
  movingBy[source] = on;
  const any = Object.values(movingBy).some(Boolean) || state.actionInFlight > 0 || (state.job && !state.jobEnded);
  $("stop").hidden = !any;
}

async function stopAll() {
  try {
    const out = await api("POST", "/stage/stop", { bench: state.bench });
    $("move-result").textContent = `stopped${out.failed_job ? `; job ${out.failed_job} failed` : ""}`;
    $("stop").dataset.stopped = "1";
  } catch (err) {
    showProblem(err.message);
  }
}

async function action(button, fn) {
  state.actionInFlight += 1; setMoving(true, "action");
  button.disabled = true;
  try { return await fn(); } finally {
    button.disabled = false;
    state.actionInFlight -= 1;
    setMoving(false, "action");
  }
}

const operateMessage = (err) => (err.status === 403 ? `${err.message} (this needs a token with the operate scope)` : err.message);

// ------------------------------------------------------------------ run: calibration jobs

function planned(grid) {
  if (!grid) return [];
  if (grid.points) return grid.points.map(([x, y]) => [x, y]);
  const lin = (a, b, n) => Array.from({ length: n }, (_, i) => (n === 1 ? a : a + (b - a) * i / (n - 1)));
  const out = [];
  for (const y of lin(grid.y_deg[0], grid.y_deg[1], grid.n_y)) for (const x of lin(grid.x_deg[0], grid.x_deg[1], grid.n_x)) out.push([x, y]);
  return out;
}

function drawGrid() {
  const svg = $("grid");
  const job = state.job;
  svg.replaceChildren();
  if (!job) return;
  const plan = planned((job.request || {}).grid);
  const pts = [...state.jobPoints.values()];
  const all = [...plan, ...pts.map((p) => [p.x_deg, p.y_deg ?? 0])];
  const span = Math.max(1e-9, ...all.map(([x, y]) => Math.max(Math.abs(x), Math.abs(y))));
  const sx = (x) => (100 * x / span).toFixed(2), sy = (y) => (-100 * y / span).toFixed(2);
  svg.append(svgEl("line", { x1: -110, y1: 0, x2: 110, y2: 0, class: "axis" }), svgEl("line", { x1: 0, y1: -110, x2: 0, y2: 110, class: "axis" }));
  svg.append(svgEl("text", { x: 108, y: 112, class: "tick", "text-anchor": "end" }, `X ±${+span.toPrecision(4)}°`));
  svg.append(svgEl("text", { x: 4, y: -108, class: "tick" }, `Y ±${+span.toPrecision(4)}°`));
  for (const [x, y] of plan) svg.append(svgEl("circle", { cx: sx(x), cy: sy(y), r: 5, class: "planned" }));
  let last = null;
  for (const p of pts) {
    const c = svgEl("circle", { cx: sx(p.x_deg), cy: sy(p.y_deg ?? 0), r: 5, class: "measured", "data-index": p.index });
    c.append(svgEl("title", {}, `point ${p.index}: X ${deg(p.x_deg)}, Y ${deg(p.y_deg)}`));
    svg.append(c);
    if (!last || p.index > last.index) last = p;
  }
  if (last) svg.append(svgEl("circle", { cx: sx(last.x_deg), cy: sy(last.y_deg ?? 0), r: 9, class: "current" }));
  svg.dataset.measured = String(pts.length);
}

function showJob(job) {
  state.job = job;
  const p = job.progress || {};
  $("job-id").textContent = `#${job.id}`;
  $("job-state").textContent = job.state;
  $("job-state").className = `st-${job.state}`;
  $("job-phase").textContent = p.phase || "—";
  $("job-progress").textContent = `${p.points_done ?? 0} of ${p.points_total ?? "?"}`;
  const done = ["succeeded", "failed", "cancelled"].includes(job.state);
  $("job-cancel").hidden = done;
  const v = job.validation;
  $("job-result").textContent = job.error ? `error: ${job.error}` : v ? `validation RMS ${degArc(v.rms_deg)}, max ${degArc(v.max_deg)} over ${v.n_points} points` : "";
  $("job-open-record").hidden = !job.record;
  if (done) { state.jobEnded = true; setMoving(false, "job"); } else setMoving(true, "job");
  drawGrid();
}

function followJob(id) {
  if (state.jobStream) state.jobStream.close();
  state.jobPoints = new Map(); state.jobEnded = false;
  state.jobStream = new Stream("job", () => wsUrl(`/ws/jobs/${id}`, {}), {
    onMessage: (m) => {
      if (m.type === "snapshot") { for (const p of m.points || []) state.jobPoints.set(p.index, p); showJob(m.job); }
      else if (m.type === "point") { state.jobPoints.set(m.point.index, m.point); drawGrid(); }
      else if (m.type === "job") showJob(m.job);
      else if (m.type === "end") { state.jobEnded = true; showJob(m.job); loadRecords(); }
    },
    onState: (s, info) => {
      const b = $("stream-banner");
      if (s === "lost") { b.textContent = `Job stream lost (${info.code}); reconnecting in ${(info.delay / 1000).toFixed(1)} s.`; b.hidden = false; }
    },
    shouldReconnect: () => !state.jobEnded,
  });
  state.jobStream.open();
}

// a form sent before the bench list has come: said where the answer would be, nothing is sent
function benchNotYet(out) {
  if (state.bench) return false;
  out.textContent = "the bench list is still loading; send again in a moment"; out.className = "error"; out.hidden = false;
  return true;
}

async function startCalibration(ev) {
  ev.preventDefault();
  if (benchNotYet($("cal-error"))) return;
  const f = new FormData($("cal-form"));
  const n = (k) => Number(f.get(k));
  const body = { bench: state.bench, procedure: f.get("procedure"), method: f.get("method"),
    grid: { x_deg: [n("x_min"), n("x_max")], y_deg: [n("y_min"), n("y_max")], n_x: n("n_x"), n_y: n("n_y") },
    samples_per_point: n("samples_per_point"), validation: { n_points: n("n_validation") },
    settle: { tolerance_deg: n("settle_tolerance_deg") } };
  $("cal-error").hidden = true;
  try {
    const job = await action($("cal-start"), () => api("POST", "/calibrations", body));
    state.jobPoints = new Map();
    showJob(job);
    followJob(job.id);
  } catch (err) {
    $("cal-error").textContent = operateMessage(err); $("cal-error").hidden = false;
  }
}

async function cancelJob() {
  if (!state.job) return;
  try { showJob(await api("POST", `/calibrations/${state.job.id}/cancel`)); } catch (err) { $("cal-error").textContent = operateMessage(err); $("cal-error").hidden = false; }
}

async function levelTable(ev) {
  ev.preventDefault();
  if (benchNotYet($("level-result"))) return;
  const f = new FormData($("level-form"));
  const body = { bench: state.bench, x_deg: Number(f.get("x_deg")), y_deg: Number(f.get("y_deg")),
    tolerance_deg: Number(f.get("tolerance_deg")), max_iterations: Number(f.get("max_iterations")) };
  const out = $("level-result");
  out.className = ""; out.textContent = "levelling…";
  try {
    const r = await action($("level-go"), () => api("POST", "/stage/level", body));
    out.textContent = `${r.within_tolerance ? "within tolerance" : "NOT within tolerance"}: table X ${deg(r.achieved.x_deg)}, Y ${deg(r.achieved.y_deg)} after ${r.iterations} iteration(s); stage X ${deg(r.stage.x_deg)}, Y ${deg(r.stage.y_deg)}`;
    out.className = r.within_tolerance ? "ok" : "error";
    out.dataset.within = String(r.within_tolerance);
  } catch (err) {
    out.textContent = operateMessage(err); out.className = "error";
  }
}

async function moveStage(ev) {
  ev.preventDefault();
  if (benchNotYet($("move-result"))) return;
  const f = new FormData($("move-form"));
  const out = $("move-result");
  out.textContent = "moving…"; out.className = "";
  try {
    const r = await action($("move-go"), () => api("POST", "/stage/move", { bench: state.bench, x_deg: Number(f.get("x_deg")), y_deg: Number(f.get("y_deg")) }));
    out.textContent = `stage stands at X ${deg(r.stage.x_deg)}, Y ${deg(r.stage.y_deg)}`;
  } catch (err) {
    out.textContent = operateMessage(err); out.className = "error";
  }
}

// ------------------------------------------------------------------ a token for a LIMS (admin)

async function makeToken(ev) {
  ev.preventDefault();
  const f = new FormData($("token-form"));
  const out = $("token-result");
  out.className = ""; out.textContent = "making the token…";
  try {
    const t = await action($("token-make"), () => api("POST", "/tokens", { name: f.get("name"), scopes: [f.get("scope")] }));
    out.replaceChildren(`token ${t.name} (${t.scopes.join(", ")}): `, el("code", { id: "token-text" }, t.token),
      " (shown this once)");
    out.className = "ok";
  } catch (err) {
    out.textContent = err.status === 403 ? `${err.message} (making tokens needs a token with the admin scope)` : err.message;
    out.className = "error";
  }
}

// ------------------------------------------------------------------ records: judge a calibration

async function loadRecords() {
  try { state.records = (await api("GET", `/records?bench=${encodeURIComponent(state.bench)}`)).records; drawRecords(); } catch (err) { showProblem(err.message); }
}

// a record's instrument in the lab's words: the role it serves on the bench and, when known, the instrument
function instrumentOf(r) {
  const role = ROLE_OF_KIND[r.kind] || r.kind;
  const d = (state.devices || []).find((x) => x.role === role);
  const id = d && d.identity ? ` (${d.identity.model})` : "";  // the serial number is in the row's tooltip
  return `${role.replace(/_/g, " ")}${id}`;
}

function instrumentTitle(r) {
  const d = (state.devices || []).find((x) => x.role === (ROLE_OF_KIND[r.kind] || r.kind));
  return d && d.identity ? `${d.identity.model} s/n ${d.identity.serial}, device ${r.device_id}` : `device ${r.device_id}`;
}

function drawRecords() {
  const tb = $("records").tBodies[0];
  tb.replaceChildren(...state.records.map((r) => el("tr", { class: r.id === state.selectedRecord ? "selected" : "", "data-id": r.id,
    onclick: () => openRecord(r.id) },
  el("td", {}, `${r.id}`), el("td", { title: instrumentTitle(r) }, instrumentOf(r)), el("td", {}, r.kind), el("td", {}, `v${r.version}`), el("td", {}, r.method),
  el("td", {}, utcDate(r.created_utc)), el("td", {}, r.validation ? degArc(r.validation.rms_deg) : "—"),
  el("td", {}, r.status || "—"), el("td", {}, r.active ? "active" : ""),
  el("td", {}, r.raw_data && r.raw_data.diagnosis_id ? `diagnosis ${r.raw_data.diagnosis_id} (+ ${(r.raw_data.added_effects || []).join(", ")})` : ""))));
}

async function openRecord(id, message = "") {
  state.selectedRecord = id;
  drawRecords();
  const rec = await api("GET", `/records/${id}`);
  $("record-detail").hidden = false;
  $("rec-title").textContent = `${rec.id}: ${instrumentOf(rec)}, ${rec.kind} v${rec.version} (${rec.method})${rec.active ? ", active" : ""}, ${rec.status}`;
  const v = rec.validation || {};
  const c = rec.conditions || {};
  const rows = [["RMS error", degArc(v.rms_deg)], ["largest error", degArc(v.max_deg)], ["validation points", v.n_points ?? "—"],
    ["compared with", v.compared_with || "—"], ["mean temperature", isNum(c.temp_c_mean) ? `${c.temp_c_mean.toFixed(2)} °C` : "—"],
    ["samples per point", c.samples_per_point ?? "—"], ["created", `${utcDate(rec.created_utc)} UTC by ${rec.operator || "?"}`]];
  $("rec-validation").tBodies[0].replaceChildren(...rows.map(([k, x]) => el("tr", {}, el("th", {}, k), el("td", {}, String(x)))));
  drawBudget(rec.budget);
  // the previous version of the same device
  const prev = state.records.find((r) => r.id === rec.supersedes_id) ||
    state.records.filter((r) => r.device_id === rec.device_id && r.kind === rec.kind && r.version < rec.version).sort((a, b) => b.version - a.version)[0];
  const pv = prev && prev.validation;
  if (!prev) $("rec-compare").textContent = "first version of this device: nothing to compare with";
  else if (pv && isNum(pv.rms_deg) && isNum(v.rms_deg)) {
    const d = v.rms_deg - pv.rms_deg;
    $("rec-compare").textContent = `v${prev.version} (record ${prev.id}, ${prev.method}): RMS ${degArc(pv.rms_deg)}, max ${degArc(pv.max_deg)}; this version's RMS is ${d <= 0 ? "smaller" : "larger"} by ${arcsec(Math.abs(d), 2)}`;
  } else $("rec-compare").textContent = `v${prev.version} (record ${prev.id}) has no validation figures`;
  $("dl-cert").disabled = rec.status !== "approved";
  $("dl-cert").title = rec.status === "approved" ? "" : "certificates are issued for approved records only";
  $("rec-activate").disabled = rec.active;
  $("rec-msg").textContent = message;  // what was just done to this record stays said after the redraw
  $("record-detail").dataset.id = String(rec.id);
  $("dl-model").onclick = () => download(`/records/${id}/model`, `record-${id}-MODEL.json`);
  $("dl-points").onclick = () => download(`/records/${id}/points`, `record-${id}-points.csv`);
  $("dl-cert").onclick = () => download(`/records/${id}/certificate`, `record-${id}-certificate.xml`);
  $("rec-activate").onclick = async () => {
    try {
      await api("POST", `/records/${id}/activate`);
      $("rec-msg").textContent = `record ${id} is now active`;
      await loadRecords();
      await openRecord(id, `record ${id} is now active`);
    } catch (err) { $("rec-msg").textContent = operateMessage(err); }
  };
  setupDiagnosis(rec);
  $("res-before").replaceChildren(); $("res-after").replaceChildren();
  $("res-rms-before").textContent = "—"; $("res-rms-after").textContent = "—";
  if (rec.kind !== "stage") { $("res-scale").textContent = "(residual maps are drawn for stage records)"; return; }
  try {
    const res = await api("GET", `/records/${id}/residuals`);
    $("res-scale").textContent = `(${res.points.length} points)`;
    $("res-rms-before").textContent = degArc(res.rms_before_deg);
    $("res-rms-after").textContent = degArc(res.rms_after_deg);
    drawResiduals($("res-before"), res.points, "before");
    drawResiduals($("res-after"), res.points, "after");
  } catch (err) {
    $("res-scale").textContent = `(${err.message})`;
  }
}

// ------------------------------------------------------------------ diagnosis: the discrepancy workflow on a record

function gapText(g) { return g ? `RMS ${degArc(g.rms)}, max ${degArc(g.max)}` : "—"; }

function drawDiagnosis(d) {
  const running = d.state === "queued" || d.state === "running";
  $("diag-state").textContent = running ? `diagnosis ${d.id}: ${d.state}${d.phase ? ` (${d.phase})` : ""}…`
    : d.state === "failed" ? `diagnosis ${d.id} failed: ${d.error}` : `diagnosis ${d.id}: ${d.conclusion || "done"}`;
  $("diag-state").dataset.state = d.state;
  $("diag-result").hidden = d.state !== "succeeded";
  $("diag-report").hidden = d.state !== "succeeded";
  $("diag-adopt").hidden = d.state !== "succeeded" || !(d.named_effects || []).length;
  if (d.state !== "succeeded") return;
  const rows = [["named effects", d.named_effects.length ? d.named_effects.join(", ") : "none beyond the baseline"],
    ...d.effects.map((e) => [e.effect, e.summary]),
    ["gap before", gapText(d.gap_before_deg)], ["gap after", gapText(d.gap_after_deg)],
    ["noise of a point", degArc(d.noise_deg)]];
  $("diag-result").tBodies[0].replaceChildren(...rows.map(([k, x]) => el("tr", {}, el("th", {}, k), el("td", {}, String(x)))));
  $("diag-report").onclick = () => download(`/diagnoses/${d.id}/report`, `diagnosis-${d.id}.html`);
  $("diag-adopt").onclick = async () => {
    try {
      const r = await action($("diag-adopt"), () => api("POST", `/diagnoses/${d.id}/adopt`));
      await loadRecords();
      await openRecord(r.id, `record ${r.id} (v${r.version}) made from diagnosis ${d.id}: ${d.named_effects.join(", ")} added`);
    } catch (err) { $("diag-msg").textContent = operateMessage(err); }
  };
}

async function followDiagnosis(recordId, id) {
  for (;;) {
    if (state.selectedRecord !== recordId) return;  // another record opened: stop following
    const d = await api("GET", `/diagnoses/${id}`);
    if (state.selectedRecord !== recordId) return;
    drawDiagnosis(d);
    if (d.state !== "queued" && d.state !== "running") return;
    await new Promise((res) => setTimeout(res, 1000));
  }
}

async function setupDiagnosis(rec) {
  $("diag-state").textContent = ""; $("diag-msg").textContent = "";
  $("diag-result").hidden = true; $("diag-adopt").hidden = true; $("diag-report").hidden = true;
  $("diag-start").disabled = rec.kind !== "stage" || !rec.job_id;
  $("diag-start").onclick = async () => {
    $("diag-msg").textContent = "";
    try {
      const d = await action($("diag-start"), () => api("POST", `/records/${rec.id}/diagnose`, { sensor: "ref", baseline: "kinematic" }));
      followDiagnosis(rec.id, d.id);
    } catch (err) { $("diag-msg").textContent = operateMessage(err); }
  };
  try {  // the latest diagnosis of this record, if any
    const list = (await api("GET", `/diagnoses?record=${rec.id}&limit=1`)).diagnoses;
    if (list.length) followDiagnosis(rec.id, list[0].id);
  } catch (err) { $("diag-msg").textContent = err.message; }
}

// every result's GUM budget: each contribution's standard uncertainty, then u_c, k and U at 95 %
function drawBudget(budget) {
  const tb = $("rec-budget").tBodies[0];
  const results = (budget && budget.results) || [];
  if (!results.length) { tb.replaceChildren(el("tr", {}, el("td", { colspan: "4" }, "no budget kept with this record"))); return; }
  const g = (x) => (isNum(x) ? x.toPrecision(2) : "—");
  const nu = (x) => (isNum(x) ? x.toFixed(0) : "∞");
  const rows = [];
  for (const r of results) {
    const unit = r.unit === "deg" ? "°" : ` ${r.unit}`;
    r.contributions.forEach((c, i) => rows.push(el("tr", {}, el("td", {}, i === 0 ? r.name : ""),
      el("td", {}, c.source === "fit" ? "fit (covariance, reading noise)" : c.name || c.source), el("td", {}, `${g(c.u)}${unit}`), el("td", {}, nu(c.dof)))));
    rows.push(el("tr", { class: "total" }, el("td", {}, ""), el("th", {}, `combined: U = ${g(r.U)}${unit} (k = ${r.k.toFixed(2)}, ${Math.round(100 * r.coverage_probability)} %)`),
      el("td", {}, `${g(r.u)}${unit}`), el("td", {}, nu(r.dof_eff))));
  }
  tb.replaceChildren(...rows);
}

function colour(f) {  // 0 green .. 1 red
  const h = 120 * (1 - Math.min(1, Math.max(0, f)));
  return `hsl(${h.toFixed(0)} 70% 42%)`;
}

// The residual map: points at most 80 units from the centre, the longest arrow 20 units long, so
// every arrow stays inside the frame (±110); labels and the colour scale sit outside the frame.
const MAP_R = 80, MAP_ARROW = 20, MAP_FRAME = 110;

function drawResiduals(svg, points, which) {
  svg.replaceChildren();
  const span = Math.max(1e-9, ...points.map((p) => Math.max(Math.abs(p.stage_x_deg), Math.abs(p.stage_y_deg))));
  const mag = points.map((p) => Math.hypot(p[`${which}_x_deg`], p[`${which}_y_deg`]));
  const big = Math.max(1e-12, ...mag);
  const sx = (x) => MAP_R * x / span, sy = (y) => -MAP_R * y / span;
  const gain = MAP_ARROW / big;  // map units per degree of residual
  const F = MAP_FRAME;
  const gid = `scale-${svg.id}`;
  const grad = svgEl("linearGradient", { id: gid, x1: 0, y1: 1, x2: 0, y2: 0 });
  for (const f of [0, 0.25, 0.5, 0.75, 1]) grad.append(svgEl("stop", { offset: f, "stop-color": colour(f) }));
  const defs = svgEl("defs", {});
  defs.append(grad);
  svg.append(defs);
  svg.append(svgEl("rect", { x: -F, y: -F, width: 2 * F, height: 2 * F, class: "frame" }));
  svg.append(svgEl("line", { x1: -F, y1: 0, x2: F, y2: 0, class: "axis" }), svgEl("line", { x1: 0, y1: -F, x2: 0, y2: F, class: "axis" }));
  // axes: X under the frame, Y along its left side
  svg.append(svgEl("text", { x: 0, y: F + 11, class: "tick x-label", "text-anchor": "middle" }, `stage X / ° (edge points ±${+span.toPrecision(3)}°)`));
  svg.append(svgEl("text", { x: -F - 5, y: 0, class: "tick y-label", "text-anchor": "middle", transform: `rotate(-90 ${-F - 5} 0)` },
    `stage Y / ° (edge points ±${+span.toPrecision(3)}°)`));
  // the arrow scale under the frame: a bar as long as the longest arrow, its length in arc seconds
  svg.append(svgEl("line", { x1: -F, y1: F + 24, x2: -F + MAP_ARROW, y2: F + 24, stroke: "#1d232a", "stroke-width": 2, class: "arrow-scale" }));
  svg.append(svgEl("text", { x: -F + MAP_ARROW + 4, y: F + 27, class: "res-label longest" }, `longest arrow ${arcsec(big, 1)}`));
  // the colour scale at the right of the frame: 0 at the bottom, the longest arrow at the top
  const cx = F + 6;
  svg.append(svgEl("rect", { x: cx, y: -F, width: 7, height: 2 * F, fill: `url(#${gid})`, class: "colour-scale" }));
  svg.append(svgEl("text", { x: cx + 10, y: -F + 7, class: "tick" }, arcsec(big, 1)));
  svg.append(svgEl("text", { x: cx + 10, y: F, class: "tick" }, "0″"));
  points.forEach((p, i) => {
    const x0 = sx(p.stage_x_deg), y0 = sy(p.stage_y_deg);
    const x1 = x0 + gain * p[`${which}_x_deg`], y1 = y0 - gain * p[`${which}_y_deg`];
    const c = colour(mag[i] / big);
    const g = svgEl("g", { class: `res ${p.role}`, "data-point": p.point });
    g.append(svgEl("title", {}, `point ${p.point} (${p.role}): ${which} ${arcsec(p[`${which}_x_deg`], 2)} in X, ${arcsec(p[`${which}_y_deg`], 2)} in Y`));
    g.append(svgEl("circle", { cx: x0.toFixed(2), cy: y0.toFixed(2), r: 3, fill: p.role === "fit" ? c : "#fff", stroke: c }));
    g.append(svgEl("line", { x1: x0.toFixed(2), y1: y0.toFixed(2), x2: x1.toFixed(2), y2: y1.toFixed(2), stroke: c, "stroke-width": 2 }));
    const a = Math.atan2(y1 - y0, x1 - x0), L = 6;
    if (Math.hypot(x1 - x0, y1 - y0) > 2) {
      g.append(svgEl("polygon", { fill: c, points: [[x1, y1], [x1 - L * Math.cos(a - 0.4), y1 - L * Math.sin(a - 0.4)],
        [x1 - L * Math.cos(a + 0.4), y1 - L * Math.sin(a + 0.4)]].map((q) => q.map((v) => v.toFixed(2)).join(",")).join(" ") }));
    }
    svg.append(g);
  });
  svg.dataset.points = String(points.length);
}

async function download(path, name) {
  try {
    const blob = await api("GET", path);
    const data = blob instanceof Blob ? blob : new Blob([JSON.stringify(blob, null, 2)], { type: "application/json" });
    const url = URL.createObjectURL(data);
    const a = el("a", { href: url, download: name });
    document.body.append(a); a.click(); a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
    $("rec-msg").textContent = `downloaded ${name}`;
  } catch (err) {
    $("rec-msg").textContent = err.message;
  }
}

// ------------------------------------------------------------------ views and start-up

function showView(name) {
  for (const b of $("tabs").querySelectorAll("button")) b.setAttribute("aria-selected", String(b.dataset.view === name));
  for (const v of document.querySelectorAll(".view")) v.hidden = v.id !== `view-${name}`;
  if (name === "live") {
    live.dirty = true;
    if (tiltChart) { tiltChart.setSize(chartSize($("chart-tilt"))); rawChart.setSize(chartSize($("chart-raw"))); }
  }
  if (name === "records") loadRecords();
}

async function start() {
  if (!token) {
    showAuth("No access token", "This page needs a token: the address tiltlab serve prints ends in #token=…");
    return;
  }
  // every control answers from the first moment (a tab clicked while the bench list loads opens it;
  // a form sent then says the list is still loading rather than reloading the page)
  for (const b of $("tabs").querySelectorAll("button")) b.addEventListener("click", () => showView(b.dataset.view));
  $("bench-select").addEventListener("change", (e) => { state.bench = e.target.value; openReadings(); refreshStatus(); });
  $("window").addEventListener("change", (e) => { live.windowS = Number(e.target.value); live.dirty = true; openReadings(); });
  $("rate").addEventListener("change", () => openReadings());
  $("stop").addEventListener("click", stopAll);
  $("cal-form").addEventListener("submit", startCalibration);
  $("job-cancel").addEventListener("click", cancelJob);
  $("job-open-record").addEventListener("click", () => { showView("records"); openRecord(state.job.record.id); });
  $("level-form").addEventListener("submit", levelTable);
  $("move-form").addEventListener("submit", moveStage);
  $("token-form").addEventListener("submit", makeToken);
  try {
    await loadBenches();
  } catch (err) {
    if (err.status !== 401 && err.status !== 403) showProblem(err.message);
    return;
  }
  if (!state.bench) { showProblem("the daemon runs no bench"); return; }
  document.body.dataset.bench = state.bench;  // the page knows its bench: its actions can be sent
  makeCharts();
  openReadings();
  refreshStatus();
  requestAnimationFrame(frame);
  // a job already running on the bench: follow it
  try {
    const running = (await api("GET", `/calibrations?state=running&bench=${encodeURIComponent(state.bench)}&limit=1`)).jobs[0];
    if (running) { showJob(running); followJob(running.id); }
  } catch (_) { /* shown by the status poll */ }
}

start();
