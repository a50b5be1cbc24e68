// @ts-check
// A record's diagnosis: the discrepancy workflow on its stored points (no bench), followed to its end; the
// residual maps before and after the named effects side by side; whether each named effect can be adopted
// (and, if not, the measurement that would separate it); the designed measurement's plan, or the measurement
// itself; the named effects adopted as a new version, and the record each diagnosis made.

import { api, errorText, operateMessage } from "../api.js";
import { byId, byIdAs, el, setText } from "../dom.js";
import { deg, degArc, durationText, isNum } from "../format.js";
import { action } from "../motion.js";
import { shared } from "../state.js";
import { drawResiduals } from "./residuals.js";

/** @typedef {import("../types.js").Diagnosis} Diagnosis */
/** @typedef {import("../types.js").CalibrationRecord} CalibrationRecord */
/** @typedef {import("../types.js").MeasurementPlan} MeasurementPlan */

/** @type {{selected: () => number | null, download: (path: string, name: string) => Promise<void>, adopted: (id: number, message: string) => Promise<void>, open: (id: number, diagnosis?: number) => Promise<void>}} */
const hooks = { selected: () => null, download: async () => {}, adopted: async () => {}, open: async () => {} };

/** @param {typeof hooks} given */
export function onDiagnosis(given) {
  Object.assign(hooks, given);
}

/** @param {import("../types.js").Gap | null} gap */
const gapText = (gap) => (gap ? `RMS ${degArc(gap.rms)}, max ${degArc(gap.max)}` : "—");

/** @param {number} dir */
const approachText = (dir) => (dir < 0 ? "from above" : "from below");

/**
 * The designed measurement: what it tests and why, its points with their approach directions, its estimated bench
 * time, and what cannot be measured on this bench.
 * @param {MeasurementPlan | null | undefined} plan
 * @param {string} heading
 */
function drawPlan(plan, heading) {
  const out = byId("diag-plan-out");
  if (!plan || !(plan.points?.length || plan.cannot?.length)) {
    out.hidden = true;
    out.replaceChildren();
    return;
  }
  const parts = (plan.parts || []).map((p, i) => el("tr", { "data-effect": p.effect, "data-part": i }, el("th", {}, p.effect),
    el("td", { class: "wrap" }, [p.why, p.measurement].filter(Boolean).join("; ")), el("td", {}, `${p.n_points ?? "?"} points`)));
  const cannot = (plan.cannot || []).map((c) => el("li", { "data-effect": c.effect }, `${c.effect}: ${c.reason}`));
  const points = (plan.points || []).map((p, i) => el("tr", {}, el("td", {}, `${i + 1}`), el("td", {}, deg(p.stage_x_deg)),
    el("td", {}, deg(p.stage_y_deg)), el("td", {}, `X ${approachText(p.dir_x)}, Y ${approachText(p.dir_y)}`)));
  const time = isNum(plan.estimated_bench_s) ? `about ${durationText(plan.estimated_bench_s)} of bench time` : "bench time not estimated";
  out.replaceChildren(el("h4", {}, heading),
    el("p", { class: "plan-summary" }, `${plan.n_points ?? points.length} points, ${time}`
      + `${plan.estimate_source ? ` (${plan.estimate_source})` : ""}${plan.summary ? `: ${plan.summary}` : ""}`),
    ...(parts.length ? [el("div", { class: "scroll" }, el("table", { class: "plan-parts" }, el("tbody", {}, ...parts)))] : []),
    ...(cannot.length ? [el("p", {}, "cannot be measured here:"), el("ul", { class: "plan-cannot" }, ...cannot)] : []),
    ...(points.length ? [el("details", {}, el("summary", {}, `the ${points.length} points and their approach directions`),
      el("div", { class: "scroll" }, el("table", { class: "plan-points" },
        el("thead", {}, el("tr", {}, el("th", {}, "#"), el("th", {}, "stage X"), el("th", {}, "stage Y"), el("th", {}, "approached"))),
        el("tbody", {}, ...points))))] : []));
  out.dataset.points = String(points.length);
  out.hidden = false;
}

/**
 * Per named effect: adoptable, or why not and the measurement that would separate it.
 * @param {import("../types.js").Adoption[]} adoption
 * @param {boolean | null | undefined} adoptable
 */
function drawAdoption(adoption, adoptable) {
  const out = byId("diag-adoption");
  if (!adoption.length) {
    out.hidden = true;
    out.replaceChildren();
    return;
  }
  out.replaceChildren(el("p", { class: adoptable === false ? "warning" : "" },
    adoptable === false ? "adoptable: no, none of the named effects can be adopted from these points" : "adoptable: yes"),
  el("ul", {}, ...adoption.map((a) => el("li", { "data-effect": a.effect, "data-adoptable": String(a.adoptable) },
    a.adoptable ? `${a.effect}: adoptable${a.reason ? ` (${a.reason})` : ""}`
      : `${a.effect}: not adoptable: ${a.reason}${a.measurement ? `; the measurement that would separate it: ${a.measurement}` : ""}`))));
  out.dataset.adoptable = String(adoptable);
  out.hidden = false;
}

/** The residual maps of a diagnosis, before and after its named effects, side by side on one scale. @param {Diagnosis} d */
function drawMaps(d) {
  const box = byId("diag-maps-box");
  const maps = d.residual_maps;
  if (d.state !== "succeeded" || !maps || !maps.stage_deg?.length) {
    box.hidden = true;
    return;
  }
  const points = maps.stage_deg.map(([x, y], i) => {
    const dirs = maps.approach?.[i] || [1, 1];
    return { point: i + 1, role: dirs[0] < 0 || dirs[1] < 0 ? "above" : "below", stage_x_deg: x, stage_y_deg: y,
      ref_x_deg: x, ref_y_deg: y, before_x_deg: maps.before_deg[i][0], before_y_deg: maps.before_deg[i][1],
      after_x_deg: maps.after_deg[i][0], after_y_deg: maps.after_deg[i][1] };
  });
  const scale = Math.max(1e-12, ...points.map((p) => Math.max(Math.hypot(p.before_x_deg, p.before_y_deg), Math.hypot(p.after_x_deg, p.after_y_deg))));
  box.hidden = false; // drawn while shown: the labels' boxes are measured by the browser
  drawResiduals(byId("diag-before"), points, "before", scale);
  drawResiduals(byId("diag-after"), points, "after", scale);
  setText("diag-maps-id", String(d.id));
  setText("diag-rms-before", d.gap_before_deg ? degArc(d.gap_before_deg.rms) : "—");
  setText("diag-rms-after", d.gap_after_deg ? degArc(d.gap_after_deg.rms) : "—");
  setText("diag-effects", d.named_effects.length ? d.named_effects.join(", ") : "no effect named");
  byId("diag-before").dataset.diagnosis = byId("diag-after").dataset.diagnosis = String(d.id);
}

/** The record a diagnosis made, when one was adopted from it. @param {Diagnosis} d */
function drawMade(d) {
  const out = byId("diag-made");
  const made = shared.records.filter((r) => r.raw_data?.diagnosis_id === d.id);
  if (!made.length) {
    out.hidden = true;
    out.replaceChildren();
    return;
  }
  out.replaceChildren(`diagnosis ${d.id} made `, ...made.flatMap((r, i) => {
    const link = el("button", { type: "button", class: "link", "data-record": r.id }, `record ${r.id} (v${r.version})`);
    link.addEventListener("click", () => { void hooks.open(r.id); });
    return i ? [", ", link] : [link];
  }));
  out.hidden = false;
}

/** @param {Diagnosis} d */
function drawDiagnosis(d) {
  const running = d.state === "queued" || d.state === "running";
  const state = byId("diag-state");
  state.textContent = running ? `diagnosis ${d.id}: ${d.state}${d.phase ? ` (${d.phase})` : ""}…`
    : d.state === "failed" ? `diagnosis ${d.id} failed: ${d.error}` : `diagnosis ${d.id}: ${d.conclusion || "done"}`;
  state.dataset.state = d.state;
  state.dataset.diagnosis = String(d.id);
  const done = d.state === "succeeded";
  byId("diag-result-box").hidden = !done;
  byId("diag-report").hidden = !done;
  byId("diag-adopt").hidden = !done || !d.named_effects.length || d.adoptable === false;
  drawMaps(d);
  drawMade(d);
  if (d.measurement?.plan) drawPlan(d.measurement.plan, `the measurement this diagnosis ran${d.measurement.job_id ? ` (job ${d.measurement.job_id})` : ""}`);
  if (!done) return;
  drawAdoption(d.adoption || [], d.adoptable);
  if (!d.measurement?.plan) drawPlan(d.measurement_plan, "the measurement that would test what these points cannot");
  const rows = [["named effects", d.named_effects.length ? d.named_effects.join(", ") : "none beyond the baseline"],
    ...d.effects.map((e) => [e.effect, e.summary]),
    ...(d.untestable || []).map((u) => [`${u.effect} (not tested)`, u.reason]),
    ["gap before", gapText(d.gap_before_deg)], ["gap after", gapText(d.gap_after_deg)], ["noise of a point", degArc(d.noise_deg)]];
  byIdAs("diag-result", HTMLTableElement).tBodies[0].replaceChildren(...rows.map(([k, v]) => el("tr", {}, el("th", {}, k), el("td", {}, String(v)))));
  byId("diag-report").onclick = () => hooks.download(`/diagnoses/${d.id}/report`, `diagnosis-${d.id}.html`);
  byId("diag-adopt").onclick = async () => {
    try {
      /** @type {CalibrationRecord} */
      const made = await action(byIdAs("diag-adopt", HTMLButtonElement), () => api("POST", `/diagnoses/${d.id}/adopt`));
      await hooks.adopted(made.id, `record ${made.id} (v${made.version}) made from diagnosis ${d.id}: ${d.named_effects.join(", ")} added`);
    } catch (err) {
      setText("diag-msg", operateMessage(err));
    }
  };
}

/** @param {number} recordId @param {number} id */
async function follow(recordId, id) {
  for (;;) {
    if (hooks.selected() !== recordId) return; // another record opened: stop following
    /** @type {Diagnosis} */
    const d = await api("GET", `/diagnoses/${id}`);
    if (hooks.selected() !== recordId) return;
    drawDiagnosis(d);
    if (d.state !== "queued" && d.state !== "running") return;
    await new Promise((resolve) => setTimeout(resolve, 1000));
  }
}

/** Where a record came from: the diagnosis that made it (on the record it was adopted from). @param {CalibrationRecord} record */
function drawOrigin(record) {
  const out = byId("rec-origin");
  const from = record.raw_data?.diagnosis_id;
  if (!from) {
    out.hidden = true;
    out.replaceChildren();
    return;
  }
  const parent = record.raw_data?.adopted_from_record_id;
  const link = el("button", { type: "button", class: "link", id: "rec-origin-link", "data-diagnosis": from }, `diagnosis ${from}`);
  link.addEventListener("click", () => { if (parent) void hooks.open(parent, from); });
  out.replaceChildren("made from ", link, `${parent ? ` of record ${parent}` : ""}: `
    + `${(record.raw_data?.added_effects || []).join(", ") || "no effect"} added`);
  out.hidden = false;
}

/**
 * @param {CalibrationRecord} record
 * @param {number | null} [diagnosisId] the diagnosis to show (else the record's latest)
 */
export async function setupDiagnosis(record, diagnosisId = null) {
  setText("diag-state", "");
  setText("diag-msg", "");
  for (const id of ["diag-result-box", "diag-adopt", "diag-report", "diag-maps-box", "diag-adoption", "diag-made", "diag-plan-out"]) byId(id).hidden = true;
  drawOrigin(record);
  const start = byIdAs("diag-start", HTMLButtonElement);
  const plan = byIdAs("diag-plan", HTMLButtonElement);
  const measure = byIdAs("diag-measure", HTMLButtonElement);
  start.disabled = plan.disabled = measure.disabled = record.kind !== "stage" || !record.job_id;
  const body = { sensor: "ref", baseline: "kinematic" };
  start.onclick = async () => {
    setText("diag-msg", "");
    try {
      /** @type {Diagnosis} */
      const d = await action(start, () => api("POST", `/records/${record.id}/diagnose`, body));
      void follow(record.id, d.id);
    } catch (err) {
      setText("diag-msg", operateMessage(err));
    }
  };
  plan.onclick = async () => {
    setText("diag-msg", "");
    try {
      /** @type {import("../types.js").DiagnosisPlan} */
      const answer = await action(plan, () => api("POST", `/records/${record.id}/diagnose`, { ...body, plan_only: true }));
      if (hooks.selected() !== record.id) return;
      drawAdoption(answer.adoption, answer.adoptable);
      drawPlan(answer.plan, `the measurement that would test what the ${answer.n_points} stored points cannot (nothing moved)`);
      if (!answer.plan.points?.length && !answer.plan.cannot?.length) setText("diag-msg", "the stored points test every candidate: nothing to measure");
    } catch (err) {
      setText("diag-msg", operateMessage(err));
    }
  };
  measure.onclick = async () => {
    setText("diag-msg", "");
    try {
      /** @type {Diagnosis} */
      const d = await action(measure, () => api("POST", `/records/${record.id}/diagnose`, { ...body, measure: true }));
      void follow(record.id, d.id);
    } catch (err) {
      setText("diag-msg", operateMessage(err));
    }
  };
  if (diagnosisId) {
    void follow(record.id, diagnosisId);
    return;
  }
  try { // the latest diagnosis of this record, if any
    /** @type {{diagnoses: Diagnosis[]}} */
    const answer = await api("GET", `/diagnoses?record=${record.id}&limit=1`);
    if (answer.diagnoses.length) void follow(record.id, answer.diagnoses[0].id);
  } catch (err) {
    setText("diag-msg", errorText(err));
  }
}
