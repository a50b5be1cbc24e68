// tiltlab dashboard: polls the service's /tilt and /health and draws what it answers.
"use strict";

const POLL_MS = 1000;
const STALE_MS = 3000;
const TRACE_LENGTH = 120;
const LEVEL_RANGES_DEG = [0.01, 0.1, 1, 5, 15, 90];  // the level's outer ring snaps to one of these

const trace = [];
let lastReadingAt = 0;

const $ = (id) => document.getElementById(id);

// The token arrives in the URL fragment (#token=...) and is kept for the session only.
const fragmentToken = new URLSearchParams(location.hash.slice(1)).get("token");
if (fragmentToken) {
  sessionStorage.setItem("tiltlab-token", fragmentToken);
  history.replaceState(null, "", location.pathname + location.search);
}
const token = sessionStorage.getItem("tiltlab-token");

function showProblem(text) {
  const b = $("banner");
  b.textContent = text;
  b.hidden = false;
}

function clearProblem() {
  $("banner").hidden = true;
}

async function fetchJson(path) {
  let response;
  try {
    const headers = { Accept: "application/json" };
    if (token) headers.Authorization = `Bearer ${token}`;
    response = await fetch(path, { headers, cache: "no-store" });
  } catch (err) {
    throw new Error(`no answer from the service at ${path}`);
  }
  if (!response.ok) {
    let detail = response.statusText;
    try { detail = (await response.json()).detail || detail; } catch (_) { /* not problem+json */ }
    throw new Error(`${path} answered HTTP ${response.status}: ${detail}`);
  }
  return response.json();
}

function fmtDeg(value) {
  return value === null || value === undefined ? "—" : value.toFixed(4);
}

function levelRange(values) {
  const largest = Math.max(...values.map(Math.abs));
  return LEVEL_RANGES_DEG.find((r) => largest <= r) ?? LEVEL_RANGES_DEG[LEVEL_RANGES_DEG.length - 1];
}

function drawLevel(r) {
  const range = levelRange([r.ref_x_deg, r.ref_y_deg, r.meas_x_deg, r.meas_y_deg]);
  const place = (dot, x, y) => {  // screen y grows downwards; +Y is up on the level
    dot.setAttribute("cx", (100 * x / range).toFixed(2));
    dot.setAttribute("cy", (-100 * y / range).toFixed(2));
  };
  place($("dot-ref"), r.ref_x_deg, r.ref_y_deg);
  place($("dot-meas"), r.meas_x_deg, r.meas_y_deg);
  $("level_range_deg").textContent = String(range);
}

function drawTrace() {
  const mean = (k) => trace.reduce((s, r) => s + r[k], 0) / trace.length;
  const mx = mean("ref_x_deg"), my = mean("ref_y_deg");
  const dev = trace.flatMap((r) => [Math.abs(r.ref_x_deg - mx), Math.abs(r.ref_y_deg - my)]);
  const halfSpanDeg = Math.max(...dev, 1e-6);
  const step = 600 / (TRACE_LENGTH - 1);
  const line = (k, m) => trace
    .map((r, i) => `${(i * step).toFixed(1)},${(80 - 75 * (r[k] - m) / halfSpanDeg).toFixed(1)}`)
    .join(" ");
  $("trace-x").setAttribute("points", line("ref_x_deg", mx));
  $("trace-y").setAttribute("points", line("ref_y_deg", my));
  $("trace_count").textContent = String(trace.length);
  $("trace_span_arcsec").textContent = (2 * halfSpanDeg * 3600).toFixed(1);
}

// GET /tilt nests its values; the page shows them flat.
function flatten(t) {
  const m = t.raw.measurement_sensor || {}, f = t.raw.reference_sensor || {}, s = t.stage || {};
  const tt = t.table_tilt || {};
  return {
    time_utc: t.time_utc, temp_c: t.temp_c, note: t.note,
    calibration: t.calibration ? `record ${t.calibration.record_id} v${t.calibration.version} (${t.calibration.method})` : null,
    ref_x_deg: f.x_deg, ref_y_deg: f.y_deg, meas_x_deg: m.x_deg, meas_y_deg: m.y_deg,
    stage_x_deg: s.x_deg, stage_y_deg: s.y_deg, tilt_x_deg: tt.x_deg, tilt_y_deg: tt.y_deg,
  };
}

function showReading(r) {
  for (const k of ["ref_x_deg", "ref_y_deg", "meas_x_deg", "meas_y_deg", "stage_x_deg", "stage_y_deg",
    "tilt_x_deg", "tilt_y_deg"]) {
    $(k).textContent = fmtDeg(r[k]);
  }
  $("temp_c").textContent = r.temp_c === null || r.temp_c === undefined ? "—" : r.temp_c.toFixed(2);
  $("note").textContent = r.calibration ? `calibration ${r.calibration}` : r.note;
  $("updated").textContent = `at ${new Date(r.time_utc).toISOString().slice(11, 19)} UTC`;
  trace.push(r);
  if (trace.length > TRACE_LENGTH) trace.shift();
  drawLevel(r);
  drawTrace();
}

async function loadHealth() {
  try {
    const h = await fetchJson("/health");
    $("bench").textContent = h.bench;
    $("database").textContent = h.database;
    $("schema").textContent = h.schema_revision + (h.status === "ok" ? "" : " (not at head)");
    $("version").textContent = h.version;
  } catch (err) {
    showProblem(err.message);
  }
}

async function poll() {
  try {
    showReading(flatten(await fetchJson("/tilt")));
    lastReadingAt = Date.now();
    clearProblem();
  } catch (err) {
    showProblem(err.message);
  }
  document.body.classList.toggle("stale", Date.now() - lastReadingAt > STALE_MS);
  setTimeout(poll, POLL_MS);
}

loadHealth();
poll();
