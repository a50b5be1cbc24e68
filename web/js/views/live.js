// @ts-check
// The Live view: readings over /ws/readings into a ring of the last hour, drawn once per animation frame;
// the table tilt with its expanded uncertainty; the latest raw readings; and how fresh all of it is.
// Gaps in the readings are drawn as gaps and said; a lost stream or a silent sensor marks the values stale
// with their age, in the header and on the tilt figure.

import { wsUrl } from "../api.js";
import { LiveCharts } from "../charts.js";
import { byId, byIdAs, setText } from "../dom.js";
import { deg, durationText, gumDeg, isNum, kText, uDecimals, utcClock, utcTime } from "../format.js";
import { setMoving } from "../motion.js";
import { Ring } from "../ring.js";
import { shared } from "../state.js";
import { Stream } from "../streams.js";
import { showProblem, showStreamProblem } from "./banner.js";

/** @typedef {import("../types.js").ReadingMessage} ReadingMessage */
/** @typedef {import("../types.js").TableTilt} TableTilt */

const MAX_RATE_HZ = 50;
const MAX_WINDOW_S = 3600;
const MIN_GAP_S = 1.0; // readings further apart than this (and than five intervals) have a gap between them
const AGE_TICK_MS = 250;
const HISTORY_MAX_S = 3600; // the longest history the daemon gives

/**
 * The uncertainties of an axis by their names (expanded U, standard u, coverage factor k, degrees of freedom);
 * from a daemon that sends only the deprecated aliases, U and k from `u_x_deg`/`u_y_deg` (expanded, despite the
 * name) and `k`/`k_y`, and no standard uncertainty.
 */
export const uncertainty = {
  /** @param {TableTilt} tilt @param {"x" | "y"} axis */
  expanded: (tilt, axis) => (axis === "x" ? tilt.expanded_uncertainty_x_deg ?? tilt.u_x_deg : tilt.expanded_uncertainty_y_deg ?? tilt.u_y_deg),
  /** @param {TableTilt} tilt @param {"x" | "y"} axis */
  standard: (tilt, axis) => (axis === "x" ? tilt.standard_uncertainty_x_deg : tilt.standard_uncertainty_y_deg),
  /** @param {TableTilt} tilt @param {"x" | "y"} axis */
  factor: (tilt, axis) => (axis === "x" ? tilt.coverage_factor_x ?? tilt.k : tilt.coverage_factor_y ?? tilt.k_y),
  /** @param {TableTilt} tilt @param {"x" | "y"} axis */
  dof: (tilt, axis) => (axis === "x" ? tilt.degrees_of_freedom_x : tilt.degrees_of_freedom_y),
};

/**
 * Each axis's uncertainties labelled as the GUM names them: "U (k = 2.01, 95 %) 0.0030°", "u 0.0015°" and the
 * degrees of freedom where the daemon gives them; for an averaged tilt, the readings it is the mean of.
 * @param {TableTilt} tilt
 */
export function uncertaintyText(tilt) {
  const p = isNum(tilt.coverage_probability) ? `${+(tilt.coverage_probability * 100).toPrecision(3)} %` : "95 %";
  const axes = /** @type {const} */ (["x", "y"]).map((axis) => {
    const U = uncertainty.expanded(tilt, axis), u = uncertainty.standard(tilt, axis), nu = uncertainty.dof(tilt, axis);
    const d = uDecimals(U);
    const parts = [`U (k = ${kText(uncertainty.factor(tilt, axis))}, ${p}) ${isNum(U) ? `${U.toFixed(d)}°` : "—"}`];
    if (isNum(u)) parts.push(`u ${u.toFixed(uDecimals(u))}°`);
    if (isNum(nu)) parts.push(`ν ${nu.toFixed(0)}`);
    return `${axis.toUpperCase()}: ${parts.join(", ")}`;
  });
  const mean = isNum(tilt.n_readings) ? `; the mean of ${tilt.n_readings} readings${isNum(tilt.window_s) ? ` over ${tilt.window_s.toFixed(1)} s` : ""}`
    : "; for this one reading";
  return `${axes.join("; ")}${mean}`;
}

export const ring = new Ring(Math.ceil(MAX_WINDOW_S * MAX_RATE_HZ * 1.1));

/** What the live view holds; read by the browser tests and the console (window.tiltlab.live). */
export const live = {
  received: 0, dropped: 0, draws: 0, snapshots: 0, dirty: false, windowS: 60, rateHz: 50,
  /** @type {ReadingMessage | null} */
  latest: null,
  /** @type {import("../types.js").CalibrationInUse | null | undefined} */
  calibration: undefined,
  /** performance.now() when the newest reading arrived */
  arrivedMs: 0,
  /** "open", "lost" (reconnecting) or "connecting" */
  stream: "connecting",
  stale: false,
};

/** @type {LiveCharts | null} */
let charts = null;
/** @type {Stream<ReadingMessage> | null} */
let readings = null;

export function getCharts() {
  return charts;
}

/** @param {number | null | undefined} v */
const num = (v) => (isNum(v) ? v : NaN);

/** @param {ReadingMessage} m */
function toRow(m) {
  const tilt = m.table_tilt;
  const meas = m.raw?.measurement_sensor || {}, ref = m.raw?.reference_sensor || {};
  return {
    t: new Date(m.time_utc || 0).getTime() / 1000,
    tx: tilt ? num(tilt.x_deg) : NaN, ty: tilt ? num(tilt.y_deg) : NaN,
    ux: tilt ? num(uncertainty.expanded(tilt, "x")) : NaN, uy: tilt ? num(uncertainty.expanded(tilt, "y")) : NaN,
    mx: num(meas.x_deg), my: num(meas.y_deg), rx: num(ref.x_deg), ry: num(ref.y_deg),
  };
}

/** Readings further apart than this have missing readings between them. */
function gapAfterS() {
  return Math.max(MIN_GAP_S, 5 / live.rateHz);
}

/** @param {ReadingMessage} m */
function addReading(m) {
  const row = toRow(m);
  if (!(row.t > ring.lastT)) return; // already held (a reconnect's history overlaps)
  ring.push(row, ring.len > 0 && row.t - ring.lastT > gapAfterS());
  live.latest = m;
  live.dirty = true;
}

/** @param {ReadingMessage} m */
function onMessage(m) {
  live.arrivedMs = performance.now();
  if (m.type === "snapshot") {
    // the history fills the time since the last reading held (oldest first); then the snapshot itself
    if (isNum(m.rate_hz) && m.rate_hz > 0) live.rateHz = m.rate_hz;
    for (const old of m.history || []) addReading(old);
    addReading(m);
    live.snapshots += 1;
    live.calibration = m.calibration;
    const speed = simulationSpeed(m.bench);
    const shown = isNum(m.rate_hz) ? `${m.rate_hz.toFixed(1)} Hz` : "? Hz";
    setText("stream-state", `${m.bench}, ${shown}${speed !== 1 && isNum(m.rate_hz) ? ` of bench time (${speed}× speed: ${(m.rate_hz * speed).toFixed(0)} a second)` : ""}`);
  } else if (m.type === "reading") {
    live.received += 1;
    // each reading names the record that corrected it: an activation shows with the next reading
    if (m.calibration !== undefined) live.calibration = m.calibration;
    addReading(m);
  } else if (m.type === "dropped") {
    live.dropped += m.count || 0;
  }
}

/**
 * The history a (re)connect asks for, in bench seconds (a simulated bench's run `speed` times faster than the
 * UTC times the chart is drawn over): the window, or the time since the newest reading held when that is
 * shorter (what a reconnect missed).
 */
function historyS() {
  const speed = shared.benches.find((b) => b.name === shared.bench)?.simulated?.speed || 1;
  const windowS = live.windowS * speed;
  const missedS = ring.len && live.arrivedMs ? ((performance.now() - live.arrivedMs) / 1000 + 2) * speed : windowS;
  return Math.ceil(Math.min(windowS, missedS, HISTORY_MAX_S));
}

/**
 * A screen draws at most about 60 frames a second: more messages a real second than that are parsed for nothing.
 * A simulated bench runs `speed` times faster than the clock, so its rate (in bench seconds) is asked lower.
 */
const MAX_MESSAGES_PER_REAL_S = 50;

/** The rate to ask, in bench Hz: the one chosen, at most MAX_MESSAGES_PER_REAL_S a real second. */
function askedRateHz() {
  const chosen = Number(byIdAs("rate", HTMLSelectElement).value);
  return Math.min(chosen, MAX_MESSAGES_PER_REAL_S / simulationSpeed(shared.bench));
}

/** How many times faster than the clock a bench runs (1: a real bench, or not known yet). @param {string | null | undefined} name */
function simulationSpeed(name) {
  return shared.benches.find((b) => b.name === name)?.simulated?.speed || 1;
}

export function openReadings() {
  if (readings) readings.close();
  ring.clear();
  live.latest = null;
  live.dirty = true;
  readings = new Stream("readings", () => wsUrl("/ws/readings", {
    bench: shared.bench || "", rate_hz: String(askedRateHz()),
    history_s: String(historyS()),
  }), {
    onMessage,
    onState: (state, info) => {
      if (state === "open") {
        live.stream = "open";
        showStreamProblem("");
        return;
      }
      if (state === "lost" && info) {
        live.stream = "lost";
        showStreamProblem(`Live stream lost (${info.code}${info.reason ? `: ${info.reason}` : ""}); reconnecting in`
          + ` ${(info.delay / 1000).toFixed(1)} s (attempt ${info.attempt}).`);
        setText("stream-state", "disconnected");
      }
    },
  });
  live.stream = "connecting";
  readings.open();
}

export function closeReadings() {
  if (readings) readings.close();
}

/** The values are stale when the stream is lost or no reading came for several intervals. */
function freshness() {
  const ageS = live.latest ? (performance.now() - live.arrivedMs) / 1000 : Infinity;
  const stale = live.stream !== "open" || ageS > gapAfterS();
  return { ageS, stale };
}

function showFreshness() {
  const { ageS, stale } = freshness();
  live.stale = stale;
  document.body.classList.toggle("stale", stale);
  const pill = byId("live-state");
  const age = Number.isFinite(ageS) ? `last reading ${durationText(ageS)} ago` : "no reading yet";
  pill.textContent = !stale ? "live" : live.stream === "lost" ? `stream lost: ${age}` : `no new readings: ${age}`;
  pill.className = `pill ${stale ? "stale" : "live"}`;
  pill.dataset.stale = String(stale);
  const figureAge = byId("tilt-age");
  figureAge.textContent = !live.latest ? "" : stale ? `stale: this value is ${durationText(ageS)} old` : `at ${utcTime(live.latest.time_utc)}`;
  figureAge.classList.toggle("stale", stale);
}

/** The gaps in the window, said in words (the newest three). */
function showGaps() {
  const gaps = ring.gaps(ring.lastT - live.windowS);
  const note = byId("gap-note");
  note.dataset.gaps = String(gaps.length);
  note.dataset.spans = gaps.map((g) => `${g.from} ${g.to}`).join(","); // seconds since the epoch, UTC
  note.textContent = gaps.length ? `no data ${gaps.slice(-3).map((g) => `${utcClock(g.from)}–${utcClock(g.to)} UTC`).join(", ")}`
    + (gaps.length > 3 ? ` and ${gaps.length - 3} earlier gap(s)` : "") : "";
}

function frame() {
  if (live.dirty && charts && !byId("view-live").hidden) {
    live.dirty = false;
    const { hasTilt } = charts.draw(ring, live.windowS);
    live.draws += 1;
    setText("tilt-note", hasTilt ? "" : "no corrected table tilt in this window (no active calibration record, or the sensor is silent)");
    showGaps();
    showLatest(live.latest);
  }
  setText("n-readings", String(live.received));
  setText("n-buffer", String(ring.size));
  setText("n-dropped", String(live.dropped));
  setText("n-draws", String(live.draws));
  requestAnimationFrame(frame);
}

/** @param {ReadingMessage | null} m */
function showLatest(m) {
  if (!m) return;
  const meas = m.raw?.measurement_sensor || {}, ref = m.raw?.reference_sensor || {}, stage = m.stage || {};
  setText("ref_x", deg(ref.x_deg)); setText("ref_y", deg(ref.y_deg));
  setText("meas_x", deg(meas.x_deg)); setText("meas_y", deg(meas.y_deg));
  setText("stage_x", deg(stage.x_deg)); setText("stage_y", deg(stage.y_deg));
  setText("stage_moving", stage.moving ? "moving" : "standing");
  setText("temp_c", isNum(m.temp_c) ? `${m.temp_c.toFixed(2)} °C` : "—");
  setText("updated", `at ${utcTime(m.time_utc)}`);
  const tilt = m.table_tilt;
  setText("tilt_x", tilt ? gumDeg(tilt.x_deg, uncertainty.expanded(tilt, "x")) : "—");
  setText("tilt_y", tilt ? gumDeg(tilt.y_deg, uncertainty.expanded(tilt, "y")) : "—");
  setText("tilt-u", tilt ? uncertaintyText(tilt) : "");
  const used = live.calibration;
  const factors = tilt ? `k = ${kText(uncertainty.factor(tilt, "x"))} in X, k_y = ${kText(uncertainty.factor(tilt, "y"))} in Y` : "";
  const coverage = tilt && isNum(tilt.coverage_probability) ? ` (${+(tilt.coverage_probability * 100).toPrecision(3)} % coverage)` : "";
  setText("calibration-note", tilt ? `uncertainty expanded with ${factors}${coverage}${used ? `; record ${used.record_id} v${used.version} (${used.method})` : ""}`
    : "no corrected tilt: no active calibration record, or the measurement sensor is silent");
  setMoving("stream", !!stage.moving);
}

export function markDirty() {
  live.dirty = true;
  if (charts && !byId("view-live").hidden) charts.resize();
}

export function startLive() {
  try {
    charts = new LiveCharts({ tiltX: byId("chart-tilt-x"), tiltY: byId("chart-tilt-y"), raw: byId("chart-raw") });
  } catch (err) {
    showProblem(`the charts could not be made: ${err instanceof Error ? err.message : err}`);
    return;
  }
  window.addEventListener("resize", () => charts?.resize());
  byIdAs("window", HTMLSelectElement).addEventListener("change", (event) => {
    live.windowS = Number(/** @type {HTMLSelectElement} */ (event.target).value);
    live.dirty = true;
    openReadings();
  });
  byIdAs("rate", HTMLSelectElement).addEventListener("change", () => openReadings());
  byIdAs("y-scale", HTMLSelectElement).addEventListener("change", (event) => {
    if (charts) charts.yScale = /** @type {HTMLSelectElement} */ (event.target).value === "window" ? "window" : "present";
    live.dirty = true;
  });
  openReadings();
  requestAnimationFrame(frame);
  window.setInterval(showFreshness, AGE_TICK_MS);
}
