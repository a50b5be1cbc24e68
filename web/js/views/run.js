// @ts-check
// The Run view: start a calibration and follow it over /ws/jobs/{id} on a picture of its grid; level the
// table; move the stage.

import { api, ApiError, errorText, operateMessage, wsUrl } from "../api.js";
import { byId, byIdAs, numberField, setText, svgEl, textField } from "../dom.js";
import { benchSecondsText, deg, degArc, isNum } from "../format.js";
import { action, setMoving } from "../motion.js";
import { shared } from "../state.js";
import { Stream } from "../streams.js";
import { showStreamProblem } from "./banner.js";

/** @typedef {import("../types.js").Job} Job */
/** @typedef {import("../types.js").JobPoint} JobPoint */
/** @typedef {import("../types.js").JobMessage} JobMessage */

export const run = {
  /** @type {Job | null} */
  job: null,
  /** @type {Map<number, JobPoint>} */
  points: new Map(),
  ended: false,
  /** @type {Stream<JobMessage> | null} */
  stream: null,
};

/** @type {(job: Job) => void} */
let jobEnded = () => {};
/** @type {(recordId: number) => void} */
let openRecord = () => {};

/** @param {{jobEnded: (job: Job) => void, openRecord: (recordId: number) => void}} handlers */
export function onJobs(handlers) {
  jobEnded = handlers.jobEnded;
  openRecord = handlers.openRecord;
}

/** The grid's planned stage points. @param {import("../types.js").Grid | null | undefined} grid @returns {number[][]} */
function planned(grid) {
  if (!grid) return [];
  if (grid.points) return grid.points.map(([x, y]) => [x, y]);
  if (!grid.x_deg || !grid.y_deg || !grid.n_x || !grid.n_y) return [];
  /** @param {number} a @param {number} b @param {number} n */
  const lin = (a, b, n) => Array.from({ length: n }, (_, i) => (n === 1 ? a : a + ((b - a) * i) / (n - 1)));
  const out = [];
  for (const y of lin(grid.y_deg[0], grid.y_deg[1], grid.n_y)) for (const x of lin(grid.x_deg[0], grid.x_deg[1], grid.n_x)) out.push([x, y]);
  return out;
}

function drawGrid() {
  const svg = byId("grid");
  const job = run.job;
  svg.replaceChildren();
  if (!job) return;
  const plan = planned(job.request?.grid);
  const points = [...run.points.values()];
  const all = [...plan, ...points.map((p) => [p.x_deg, p.y_deg ?? 0])];
  const span = Math.max(1e-9, ...all.map(([x, y]) => Math.max(Math.abs(x), Math.abs(y))));
  /** @param {number} x */ const sx = (x) => ((100 * x) / span).toFixed(2);
  /** @param {number} y */ const sy = (y) => ((-100 * y) / span).toFixed(2);
  svg.append(svgEl("line", { x1: -110, y1: 0, x2: 110, y2: 0, class: "axis" }), svgEl("line", { x1: 0, y1: -110, x2: 0, y2: 110, class: "axis" }));
  svg.append(svgEl("text", { x: 108, y: 112, class: "tick", "text-anchor": "end" }, `X ±${+span.toPrecision(4)}°`));
  svg.append(svgEl("text", { x: 4, y: -108, class: "tick" }, `Y ±${+span.toPrecision(4)}°`));
  for (const [x, y] of plan) svg.append(svgEl("circle", { cx: sx(x), cy: sy(y), r: 5, class: "planned" }));
  /** @type {JobPoint | null} */
  let last = null;
  for (const p of points) {
    const dot = svgEl("circle", { cx: sx(p.x_deg), cy: sy(p.y_deg ?? 0), r: 5, class: "measured", "data-index": p.index });
    dot.append(svgEl("title", {}, `point ${p.index}: X ${deg(p.x_deg)}, Y ${deg(p.y_deg)}`));
    svg.append(dot);
    if (!last || p.index > last.index) last = p;
  }
  if (last) svg.append(svgEl("circle", { cx: sx(last.x_deg), cy: sy(last.y_deg ?? 0), r: 9, class: "current" }));
  svg.dataset.measured = String(points.length);
}

/**
 * An adaptive job's design in words: its target U and, once known, the U it predicts; null for a fixed grid.
 * @param {Job} job
 */
export function designText(job) {
  if (job.request?.design !== "adaptive") return null;
  const target = job.request.target_expanded_uncertainty_deg;
  const predicted = job.predicted_expanded_uncertainty_deg ?? job.validation?.predicted_expanded_uncertainty_deg;
  return `adaptive design: target U ${isNum(target) ? degArc(target) : "—"}`
    + `${isNum(predicted) ? `; predicted U of the correction ${degArc(predicted)}` : ""}`;
}

/** @param {Job} job */
export function showJob(job) {
  run.job = job;
  const progress = job.progress;
  setText("job-id", `#${job.id}`);
  const state = byId("job-state");
  state.textContent = job.state;
  state.className = `st-${job.state}`;
  setText("job-phase", progress.phase || "—");
  setText("job-progress", `${progress.points_done ?? 0} of ${progress.points_total ?? "?"}`);
  const done = ["succeeded", "failed", "cancelled"].includes(job.state);
  byId("job-cancel").hidden = done;
  const v = job.validation;
  setText("job-result", job.error ? `error: ${job.error}` : v ? `validation RMS ${degArc(v.rms_deg)}, max ${degArc(v.max_deg)} over ${v.n_points} points` : "");
  byId("job-open-record").hidden = !job.record;
  const time = benchSecondsText(job.bench_seconds);
  const timeOut = byId("job-bench-time");
  timeOut.textContent = time ? `${job.state === "running" || job.state === "queued" ? "so far: " : ""}${time}` : "";
  timeOut.hidden = !time;
  const design = designText(job);
  byId("job-design").textContent = design || "";
  byId("job-design").hidden = !design;
  if (done) run.ended = true;
  setMoving("job", !done);
  drawGrid();
}

/** @param {number} id */
export function followJob(id) {
  if (run.stream) run.stream.close();
  run.points = new Map();
  run.ended = false;
  run.stream = new Stream("job", () => wsUrl(`/ws/jobs/${id}`, {}), {
    onMessage: (m) => {
      if (m.type === "snapshot" && m.job) {
        for (const p of m.points || []) run.points.set(p.index, p);
        showJob(m.job);
      } else if (m.type === "point" && m.point) {
        run.points.set(m.point.index, m.point);
        drawGrid();
      } else if (m.type === "job" && m.job) {
        showJob(m.job);
      } else if (m.type === "end" && m.job) {
        run.ended = true;
        showJob(m.job);
        jobEnded(m.job);
      }
    },
    onState: (state, info) => {
      if (state === "lost" && info) showStreamProblem(`Job stream lost (${info.code}); reconnecting in ${(info.delay / 1000).toFixed(1)} s.`);
    },
    shouldReconnect: () => !run.ended,
  });
  run.stream.open();
}

/** A form sent before the bench list has come: said where the answer would be, nothing is sent. @param {HTMLElement} out */
function benchNotYet(out) {
  if (shared.bench) return false;
  out.textContent = "the bench list is still loading; send again in a moment";
  out.className = "error";
  out.hidden = false;
  return true;
}

/**
 * The laboratory's ambient conditions as entered (each value with its standard uncertainty), or nothing when
 * no value is entered (the bench's ambient sensor, where it has one, records them).
 * @param {FormData} form
 * @returns {{conditions?: Record<string, {value: number, standard_uncertainty: number}>}}
 */
function conditionsOf(form) {
  /** @type {Record<string, {value: number, standard_uncertainty: number}>} */
  const conditions = {};
  for (const [key, value, u] of [["ambient_temperature_c", "ambient_c", "ambient_u_c"], ["relative_humidity_pct", "humidity_pct", "humidity_u_pct"]]) {
    if (textField(form, value).trim() === "") continue;
    conditions[key] = { value: numberField(form, value), standard_uncertainty: numberField(form, u) };
  }
  return Object.keys(conditions).length ? { conditions } : {};
}

/** @param {SubmitEvent} event */
async function startCalibration(event) {
  event.preventDefault();
  const error = byId("cal-error");
  if (benchNotYet(error)) return;
  const form = new FormData(byIdAs("cal-form", HTMLFormElement));
  /** @param {string} name */
  const n = (name) => numberField(form, name);
  const body = {
    bench: shared.bench, procedure: textField(form, "procedure"), method: textField(form, "method"),
    grid: { x_deg: [n("x_min"), n("x_max")], y_deg: [n("y_min"), n("y_max")], n_x: n("n_x"), n_y: n("n_y") },
    samples_per_point: n("samples_per_point"), validation: { n_points: n("n_validation") },
    settle: { tolerance_deg: n("settle_tolerance_deg") },
    ...conditionsOf(form),
  };
  error.hidden = true;
  try {
    /** @type {Job} */
    const job = await action(byIdAs("cal-start", HTMLButtonElement), () => api("POST", "/calibrations", body));
    run.points = new Map();
    showJob(job);
    followJob(job.id);
  } catch (err) {
    error.textContent = operateMessage(err) + (err instanceof ApiError && err.field ? ` (field ${err.field})` : "");
    error.hidden = false;
  }
}

async function cancelJob() {
  if (!run.job) return;
  try {
    showJob(await api("POST", `/calibrations/${run.job.id}/cancel`));
  } catch (err) {
    setText("cal-error", operateMessage(err));
    byId("cal-error").hidden = false;
  }
}

/** @param {SubmitEvent} event */
async function levelTable(event) {
  event.preventDefault();
  const out = byId("level-result");
  if (benchNotYet(out)) return;
  const form = new FormData(byIdAs("level-form", HTMLFormElement));
  const body = { bench: shared.bench, x_deg: numberField(form, "x_deg"), y_deg: numberField(form, "y_deg"),
    tolerance_deg: numberField(form, "tolerance_deg"), max_iterations: numberField(form, "max_iterations") };
  out.className = "";
  out.textContent = "levelling…";
  try {
    /** @type {import("../types.js").LevelResult} */
    const r = await action(byIdAs("level-go", HTMLButtonElement), () => api("POST", "/stage/level", body));
    out.textContent = `${r.within_tolerance ? "within tolerance" : "NOT within tolerance"}: table X ${deg(r.achieved.x_deg)}, Y ${deg(r.achieved.y_deg)}`
      + ` after ${r.iterations} iteration(s); stage X ${deg(r.stage.x_deg)}, Y ${deg(r.stage.y_deg)}`;
    out.className = r.within_tolerance ? "ok" : "error";
    out.dataset.within = String(r.within_tolerance);
  } catch (err) {
    out.textContent = operateMessage(err);
    out.className = "error";
  }
}

/** @param {SubmitEvent} event */
async function moveStage(event) {
  event.preventDefault();
  const out = byId("move-result");
  if (benchNotYet(out)) return;
  const form = new FormData(byIdAs("move-form", HTMLFormElement));
  out.textContent = "moving…";
  out.className = "";
  try {
    /** @type {{stage: import("../types.js").AxisPair}} */
    const r = await action(byIdAs("move-go", HTMLButtonElement),
      () => api("POST", "/stage/move", { bench: shared.bench, x_deg: numberField(form, "x_deg"), y_deg: numberField(form, "y_deg") }));
    out.textContent = `stage stands at X ${deg(r.stage.x_deg)}, Y ${deg(r.stage.y_deg)}`;
  } catch (err) {
    out.textContent = operateMessage(err);
    out.className = "error";
  }
}

/** A job already running on the bench is followed when the page opens. */
export async function followRunningJob() {
  try {
    /** @type {{jobs: Job[]}} */
    const answer = await api("GET", `/calibrations?state=running&bench=${encodeURIComponent(shared.bench || "")}&limit=1`);
    const running = answer.jobs[0];
    if (running) {
      showJob(running);
      followJob(running.id);
    }
  } catch (err) {
    void errorText(err); // the status poll says what is wrong with the daemon
  }
}

export function closeJobStream() {
  if (run.stream) run.stream.close();
}

export function startRun() {
  byIdAs("cal-form", HTMLFormElement).addEventListener("submit", startCalibration);
  byId("job-cancel").addEventListener("click", cancelJob);
  byId("job-open-record").addEventListener("click", () => { if (run.job?.record) openRecord(run.job.record.id); });
  byIdAs("level-form", HTMLFormElement).addEventListener("submit", levelTable);
  byIdAs("move-form", HTMLFormElement).addEventListener("submit", moveStage);
}
