// @ts-check
// The Records view: the bench's calibration records; one record judged: its validation, how it compares with
// the previous version (and over which grids), downloads, activation, residual maps, uncertainty budget.

import { api, ApiError, errorText, operateMessage } from "../api.js";
import { byId, byIdAs, el, setText, textField } from "../dom.js";
import { arcsec, benchSecondsText, conformityText, decisionRuleText, degArc, isNum, personText, utcDate, withStandardU } from "../format.js";
import { identityText, ROLE_OF_KIND, roleWords, shared } from "../state.js";
import { showProblem } from "./banner.js";
import { onDiagnosis, setupDiagnosis } from "./diagnosis.js";
import { drawResiduals } from "./residuals.js";
import { designText } from "./run.js";

/** @typedef {import("../types.js").CalibrationRecord} CalibrationRecord */
/** @typedef {import("../types.js").Job} Job */

/** @type {number | null} */
let selected = null;

/** A record's instrument in the lab's words: the role it serves on the bench and the instrument's model. @param {CalibrationRecord} r */
function instrumentOf(r) {
  const role = ROLE_OF_KIND[r.kind] || r.kind;
  const device = shared.devices.find((d) => d.role === role);
  return `${roleWords(role)}${device?.identity?.model ? ` (${device.identity.model})` : ""}`;
}

/** @param {CalibrationRecord} r */
function instrumentTitle(r) {
  const device = shared.devices.find((d) => d.role === (ROLE_OF_KIND[r.kind] || r.kind));
  return device?.identity ? `${identityText(device.identity)}; device ${r.device_id}` : `device ${r.device_id}`;
}

export function drawRecords() {
  byIdAs("records", HTMLTableElement).tBodies[0].replaceChildren(...shared.records.map((r) => {
    const row = el("tr", { class: r.id === selected ? "selected" : "", "data-id": r.id },
      el("td", {}, `${r.id}`), el("td", { title: instrumentTitle(r) }, instrumentOf(r)), el("td", {}, r.kind), el("td", {}, `v${r.version}`),
      el("td", {}, r.method), el("td", {}, utcDate(r.created_utc)), el("td", {}, r.validation ? degArc(r.validation.rms_deg) : "—"),
      el("td", {}, r.status || "—"), el("td", {}, r.active ? "active" : ""),
      el("td", {}, r.raw_data?.diagnosis_id ? `diagnosis ${r.raw_data.diagnosis_id} (+ ${(r.raw_data.added_effects || []).join(", ")})` : ""));
    row.addEventListener("click", () => { void openRecord(r.id); });
    return row;
  }));
}

export async function loadRecords() {
  try {
    /** @type {{records: CalibrationRecord[]}} */
    const answer = await api("GET", `/records?bench=${encodeURIComponent(shared.bench || "")}`);
    shared.records = answer.records;
    drawRecords();
  } catch (err) {
    showProblem(errorText(err));
  }
}

/** @type {Map<number, Promise<Job | null>>} the jobs of records (a record's job has ended: it no longer changes) */
const jobs = new Map();

/** The job that made a record, or null (none, or gone from this daemon's view). @param {CalibrationRecord} record */
function jobOf(record) {
  if (!record.job_id) return Promise.resolve(null);
  let asked = jobs.get(record.job_id);
  if (!asked) {
    asked = /** @type {Promise<Job>} */ (api("GET", `/calibrations/${record.job_id}`)).catch(() => null);
    jobs.set(record.job_id, asked);
  }
  return asked;
}

/**
 * The validation's verdict on the stated U: of the validation points' axis values, how many lie within their U.
 * @param {import("../types.js").ValidationFigures} v
 */
function withinU(v) {
  let n = 0, within = 0;
  for (const p of v.points || []) {
    for (const axis of /** @type {const} */ (["x", "y"])) {
      const measured = p[`measured_${axis}_deg`], reference = p[`reference_${axis}_deg`];
      const U = p[`expanded_uncertainty_${axis}_deg`] ?? p[`u_${axis}_deg`];
      if (!isNum(measured) || !isNum(reference) || !isNum(U)) continue;
      n += 1;
      if (Math.abs(measured - reference) <= U) within += 1;
    }
  }
  return n ? `; ${within} of ${n} axis values within their U` : "";
}

/**
 * A record's bench time and, for an adaptive job, its predicted U beside the validation's figures: rows added to
 * the validation table once the job is read.
 * @param {CalibrationRecord} record
 */
async function drawJobFigures(record) {
  const job = await jobOf(record);
  if (selected !== record.id) return;
  const rows = [];
  const time = benchSecondsText(record.bench_seconds ?? record.raw_data?.bench_seconds ?? job?.bench_seconds);
  if (time) rows.push(["bench time", time, "bench-time"]);
  const v = record.validation || {};
  const predicted = v.predicted_expanded_uncertainty_deg ?? record.predicted_expanded_uncertainty_deg
    ?? job?.predicted_expanded_uncertainty_deg ?? job?.validation?.predicted_expanded_uncertainty_deg;
  const design = job ? designText(job) : null;
  if (design) rows.push(["design", design, "design"]);
  if (isNum(predicted)) {
    const unresolved = v.validated_expanded_uncertainty_deg === null && isNum(v.validation_reading_u_deg)
      ? `validated U not resolved (the validation errors lie within its readings' own noise, u ${degArc(v.validation_reading_u_deg)}); ` : "";
    const validated = isNum(v.validated_expanded_uncertainty_deg) ? `validated U ${degArc(v.validated_expanded_uncertainty_deg)}; ` : unresolved;
    rows.push(["predicted and validated", `predicted U ${degArc(predicted)}; ${validated}validation RMS ${degArc(v.rms_deg)}, `
      + `largest ${degArc(v.max_deg)} over ${v.n_points ?? "?"} points${withinU(v)}`, "predicted"]);
  }
  const body = byIdAs("rec-validation", HTMLTableElement).tBodies[0];
  for (const [, , key] of rows) body.querySelector(`tr[data-row="${key}"]`)?.remove(); // drawn once, also when reopened at once
  body.append(...rows.map(([k, x, key]) =>
    el("tr", { "data-row": key }, el("th", {}, k), el("td", {}, x))));
}

/**
 * The grid a record was measured on, in words: the job's request, else the range it was fitted over.
 * @param {CalibrationRecord} record @returns {Promise<string>}
 */
async function gridOf(record) {
  if (record.job_id) {
    const job = await jobOf(record);
    if (job) {
      const grid = job.request?.grid;
      if (grid?.x_deg && grid.y_deg && grid.n_x && grid.n_y) {
        return `${grid.n_x} × ${grid.n_y} grid, stage X ${grid.x_deg[0]}° to ${grid.x_deg[1]}°, Y ${grid.y_deg[0]}° to ${grid.y_deg[1]}°`;
      }
      if (grid?.points) return `${grid.points.length} listed points`;
    } // (the job may be gone from another node's view: the record's own range says enough)
  }
  const range = record.calibrated_range;
  if (range?.x_deg && range.y_deg) {
    return `fitted over table tilts X ${range.x_deg[0].toFixed(2)}° to ${range.x_deg[1].toFixed(2)}°, Y ${range.y_deg[0].toFixed(2)}° to ${range.y_deg[1].toFixed(2)}°`;
  }
  return "grid not known";
}

/** How this version compares with the previous one of the same device, naming both grids. @param {CalibrationRecord} record */
async function compareWithPrevious(record) {
  const out = byId("rec-compare");
  const previous = shared.records.find((r) => r.id === record.supersedes_id)
    || shared.records.filter((r) => r.device_id === record.device_id && r.kind === record.kind && r.version < record.version)
      .sort((a, b) => b.version - a.version)[0];
  if (!previous) {
    out.textContent = "first version of this device: nothing to compare with";
    return;
  }
  const [thisGrid, previousGrid] = await Promise.all([gridOf(record), gridOf(previous)]);
  const now = record.validation, before = previous.validation;
  const same = thisGrid === previousGrid;
  const figures = before && isNum(before.rms_deg) && now && isNum(now.rms_deg)
    ? `RMS ${degArc(before.rms_deg)}, max ${degArc(before.max_deg)}; this version's RMS is ${now.rms_deg <= before.rms_deg ? "smaller" : "larger"} by ${arcsec(Math.abs(now.rms_deg - before.rms_deg), 2)}`
    : "no validation figures to compare";
  out.replaceChildren(`v${previous.version} (record ${previous.id}, ${previous.method}): ${figures}. `,
    el("span", { class: same ? "" : "warning", "data-grids": same ? "same" : "differ" },
      same ? `Both were measured on the same grid (${thisGrid}).`
        : `The grids differ: v${previous.version} on a ${previousGrid}; this version on a ${thisGrid}. The figures are over different ranges.`));
}

/** The laboratory's ambient conditions of the record's job, each with its standard uncertainty. @param {CalibrationRecord} record */
function drawConditions(record) {
  const c = record.conditions || {};
  /** @param {import("../types.js").Condition | null | undefined} x @param {string} unit */
  const said = (x, unit) => {
    if (!x) return "not recorded";
    const range = isNum(x.min) && isNum(x.max) ? `; ${x.min} to ${x.max} ${unit} over ${x.n_readings ?? "?"} readings` : "";
    const source = x.source === "ambient_sensor" ? " (the bench's ambient sensor)" : x.source === "request" ? " (entered with the job)" : "";
    return `${withStandardU(x.value, x.standard_uncertainty, unit)}${range}${source}`;
  };
  const rows = [["ambient temperature", said(c.ambient_temperature_c, "°C")], ["relative humidity", said(c.relative_humidity_pct, "%")],
    ["sensor temperature (mean)", isNum(c.temp_c_mean) ? `${c.temp_c_mean.toFixed(2)} °C` : "—"]];
  byIdAs("rec-conditions", HTMLTableElement).tBodies[0].replaceChildren(...rows.map(([k, x]) =>
    el("tr", { "data-condition": k }, el("th", {}, k), el("td", {}, x))));
}

/**
 * The record's reference standards with who calibrated each (the standard's own entry), or that it has none
 * and is not traceable.
 * @param {CalibrationRecord} record
 */
async function drawStandards(record) {
  const out = byId("rec-standards");
  const named = record.reference_standards || [];
  if (!named.length) {
    out.replaceChildren(el("p", { class: "warning", "data-traceable": "false" },
      record.budget?.warning || "no reference standard: not traceable", " (no certificate is issued for this record)"));
    return;
  }
  const items = await Promise.all(named.map(async (n) => {
    /** @type {import("../types.js").Standard | null} */
    let entry = null;
    try {
      entry = await api("GET", `/standards/${n.id}`);
    } catch (_) { /* said below: who calibrated it is not known to this page */ }
    const U = n.expanded_uncertainty_deg ?? entry?.expanded_uncertainty_deg;
    const k = n.coverage_factor ?? entry?.coverage_factor;
    const by = entry?.calibrated_by;
    const lab = by ? `calibrated by ${by.name}${by.accreditation ? ` (accreditation ${by.accreditation})` : ""}`
      + `${by.city ? `, ${by.city}` : ""}, ${by.country_code}` : "who calibrated it is not named: no certificate is issued for this record";
    return el("li", { "data-standard": n.id },
      `${n.name}${n.serial ? `, serial ${n.serial}` : ""}; certificate ${n.certificate_id || entry?.certificate_number || "?"}`
      + `${isNum(U) ? `; U = ${U}° (k = ${k ?? "?"})` : ""}; `,
      el("span", { class: by ? "calibrated-by" : "calibrated-by warning" }, lab),
      entry ? `; ${entry.status === "valid" ? "valid" : entry.status === "due_soon" ? "due soon" : "past due"} (due ${entry.due_on})` : "");
  }));
  if (selected !== record.id) return; // another record opened meanwhile
  out.replaceChildren(el("ul", { class: "standards", "data-traceable": "true" }, ...items));
}

/** The statements of conformity of a record whose order has a specification, in words. @param {CalibrationRecord} record */
function drawConformity(record) {
  const out = byId("rec-conformity");
  const c = record.conformity;
  if (!c) {
    out.replaceChildren(el("p", { class: "muted" }, "no specification: no statement of conformity"));
    return;
  }
  const pfa = c.largest_probability_of_false_acceptance || {};
  const rows = [];
  for (const axis of /** @type {const} */ (["x", "y"])) {
    const worst = c.worst_point?.[axis];
    const where = worst && isNum(worst.error) ? `; worst point: error ${degArc(worst.error)}`
      + `${isNum(worst.expanded_uncertainty) ? `, U ${degArc(worst.expanded_uncertainty)}` : ""}` : "";
    const p = pfa[axis];
    const risk = c.decision_rule === "simple_acceptance" && isNum(p) ? `; largest probability of false acceptance ${(100 * p).toPrecision(2)} %` : "";
    rows.push(el("tr", { "data-axis": axis, "data-conformity": c[axis] || "" },
      el("th", {}, `corrected tilt ${axis.toUpperCase()}`), el("td", {}, `${conformityText(c[axis])}${where}${risk}`)));
  }
  for (const [name, statement] of Object.entries(c.parameters || {})) {
    rows.push(el("tr", { "data-parameter": name, "data-conformity": statement || "" }, el("th", {}, name), el("td", {}, conformityText(statement))));
  }
  out.replaceChildren(el("p", {}, `specification: largest permissible error (MPE) ${degArc(c.max_permissible_error_deg)}; decision rule `,
    el("span", { class: "rule" }, decisionRuleText(c.decision_rule, c.guard_band_fraction))),
  el("div", { class: "scroll" }, el("table", { id: "conformity" }, el("tbody", {}, ...rows))));
}

/** The record's approvals: who decided, with which token, and the person behind it. @param {number} id */
async function loadApprovals(id) {
  try {
    /** @type {{status: string, approvals: import("../types.js").Approval[]}} */
    const answer = await api("GET", `/records/${id}/approvals`);
    if (selected !== id) return;
    setText("rec-status", `(${answer.status})`);
    const rows = answer.approvals.map((a) => el("tr", { "data-approval": a.id },
      el("td", {}, a.decision === "reject" ? "rejected" : a.meaning === "review" ? "reviewed" : "approved"),
      el("td", {}, utcDate(a.time_utc)), el("td", {}, a.actor), el("td", { class: "signer" }, personText(a.signer)),
      el("td", { class: "wrap" }, a.note || "")));
    byIdAs("rec-approvals", HTMLTableElement).tBodies[0].replaceChildren(...(rows.length ? rows
      : [el("tr", {}, el("td", { colspan: "5" }, "no decision yet: a draft"))]));
    const decided = answer.status !== "draft";
    byIdAs("rec-approve", HTMLButtonElement).disabled = decided;
    byIdAs("rec-reject", HTMLButtonElement).disabled = decided;
  } catch (err) {
    setText("decide-msg", errorText(err));
  }
}

/** Approve or reject: the daemon's reason when it refuses (a token without a person, the job's own operator). @param {number} id @param {"approve" | "reject"} decision */
async function decide(id, decision) {
  const note = textField(new FormData(byIdAs("decide-form", HTMLFormElement)), "note").trim();
  const out = byId("decide-msg");
  out.className = "";
  if (decision === "reject" && !note) {
    out.textContent = "a rejection needs a reason: write it in the field";
    out.className = "error";
    return;
  }
  try {
    /** @type {{approval: import("../types.js").Approval, record: {status: string}}} */
    const made = await api("POST", `/records/${id}/${decision}`, decision === "approve" ? { meaning: "approval", note } : { reason: note });
    await loadRecords();
    await openRecord(id);
    out.textContent = `record ${id} ${made.record.status} by ${personText(made.approval.signer)} (token ${made.approval.actor})`;
    out.className = "ok";
  } catch (err) {
    out.textContent = err instanceof ApiError && err.status === 403 ? `refused: ${err.message}` : errorText(err);
    out.className = "error";
    out.dataset.status = err instanceof ApiError ? String(err.status) : "";
  }
}

/** Every result's GUM budget: each contribution, then u_c, k and U. @param {import("../types.js").Budget | null | undefined} budget */
function drawBudget(budget) {
  const body = byIdAs("rec-budget", HTMLTableElement).tBodies[0];
  const results = budget?.results || [];
  if (!results.length) {
    body.replaceChildren(el("tr", {}, el("td", { colspan: "4" }, "no budget kept with this record")));
    return;
  }
  /** @param {number | null | undefined} x */ const g = (x) => (isNum(x) ? x.toPrecision(2) : "—");
  /** @param {number | null | undefined} x */ const nu = (x) => (isNum(x) ? x.toFixed(0) : "∞");
  const rows = [];
  for (const r of results) {
    const unit = r.unit === "deg" ? "°" : ` ${r.unit}`;
    r.contributions.forEach((c, i) => rows.push(el("tr", {}, el("td", {}, i === 0 ? r.name : ""),
      el("td", {}, c.source === "fit" ? "fit (covariance, reading noise)" : c.name || c.source), el("td", {}, `${g(c.standard_uncertainty)}${unit}`), el("td", {}, nu(c.dof)))));
    rows.push(el("tr", { class: "total" }, el("td", {}, ""),
      el("th", {}, `combined: U = ${g(r.expanded_uncertainty)}${unit} (k = ${r.coverage_factor.toFixed(2)}, ${Math.round(100 * r.coverage_probability)} %)`),
      el("td", {}, `${g(r.standard_uncertainty)}${unit}`), el("td", {}, nu(r.dof_eff))));
  }
  if (budget?.traceable === false) {
    rows.unshift(el("tr", { class: "not-traceable" }, el("td", { colspan: "4", class: "warning" },
      `${budget.warning || "no reference standard: not traceable"}: no standard's uncertainty is in these figures`)));
  }
  body.replaceChildren(...rows);
}

/**
 * Which U holds for what: the budget's corrected-tilt U is that of a point's mean (the readings averaged at each
 * calibration point); a single reading carries one reading's noise besides. Where the budget gives a single
 * reading's U beside it, both are said; otherwise the single reading's U is the one /tilt serves (shown now when
 * this record is the bench's active one).
 * @param {CalibrationRecord} record
 * @param {number} opened the openRecord call this draws for (a later one supersedes it)
 */
async function drawBudgetHolds(record, opened) {
  const out = byId("budget-holds");
  const tilts = (record.budget?.results || []).filter((r) => (r.quantity || "").startsWith("tilt_") || r.name.startsWith("corrected table tilt"));
  out.textContent = "";
  delete out.dataset.holds;
  if (!tilts.length) return;
  /** @param {number | null | undefined} x */ const g = (x) => (isNum(x) ? `${x.toPrecision(2)}°` : "—");
  const n = record.conditions?.samples_per_point;
  const meanOf = isNum(n) ? `the mean of ${n} readings (as each calibration point was measured)` : "the mean of a point's readings (as each calibration point was measured)";
  const axisOf = (/** @type {import("../types.js").BudgetResult} */ r) => (/(^|_)y(_|$)/.test(r.quantity || "") || /, y\b/.test(r.name) ? "Y" : "X");
  if (tilts.every((r) => r.single_reading && isNum(r.single_reading.expanded_uncertainty))) {
    out.textContent = tilts.map((r) => `${axisOf(r)}: U = ${g(r.expanded_uncertainty)} (k = ${r.coverage_factor.toFixed(2)}) holds for ${meanOf}; for a single reading U = `
      + `${g(r.single_reading?.expanded_uncertainty)}${isNum(r.single_reading?.coverage_factor) ? ` (k = ${r.single_reading.coverage_factor.toFixed(2)})` : ""}`).join(". ") + ".";
    out.dataset.holds = "both";
    return;
  }
  let now = "";
  if (record.active) {
    try {
      /** @type {{calibration: {record_id: number} | null, table_tilt: import("../types.js").TableTilt | null}} */
      const tilt = await api("GET", `/tilt?bench=${encodeURIComponent(shared.bench || "")}`);
      const t = tilt.table_tilt;
      if (t && tilt.calibration?.record_id === record.id) {
        const Ux = t.expanded_uncertainty_x_deg ?? t.u_x_deg, Uy = t.expanded_uncertainty_y_deg ?? t.u_y_deg;
        now = ` (now, for one reading: U = ${g(Ux)} in X, ${g(Uy)} in Y)`;
      }
    } catch (_) { /* the figure is a help, not the statement */ }
  }
  if (opened !== openings) return;
  out.textContent = `The budget's U of the corrected tilt (${tilts.map((r) => `${axisOf(r)} ${g(r.expanded_uncertainty)}`).join(", ")}) holds for ${meanOf}, `
    + `not for a single reading, which carries one reading's noise besides. A single corrected reading's U is the one `
    + `GET /tilt and the Live view give with each reading${now}.`;
  out.dataset.holds = "means";
}

/** @param {string} path @param {string} name */
async function download(path, name) {
  try {
    /** @type {Blob | object} */
    const got = await api("GET", path);
    const data = got instanceof Blob ? got : new Blob([JSON.stringify(got, null, 2)], { type: "application/json" });
    const url = URL.createObjectURL(data);
    const link = el("a", { href: url, download: name });
    document.body.append(link);
    link.click();
    link.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
    setText("rec-msg", `downloaded ${name}`);
  } catch (err) {
    setText("rec-msg", errorText(err));
  }
}

/** How many times a record has been opened: an answer that arrives after a later open is not drawn. */
let openings = 0;

/**
 * @param {number} id
 * @param {string} [message] what was just done to this record, said after the redraw
 * @param {number | null} [diagnosisId] a diagnosis of this record to show (else its latest)
 */
export async function openRecord(id, message = "", diagnosisId = null) {
  const opened = ++openings;
  selected = id;
  delete byId("record-detail").dataset.id; // set again once this record is drawn: until then the detail is not its
  drawRecords();
  const decided = byId("decide-msg");
  decided.textContent = "";
  delete decided.dataset.status;
  /** @type {CalibrationRecord} */
  const record = await api("GET", `/records/${id}`);
  if (opened !== openings) return; // a later open (or a reopen of this record) draws instead
  byId("record-detail").hidden = false;
  setText("rec-title", `${record.id}: ${instrumentOf(record)}, ${record.kind} v${record.version} (${record.method})${record.active ? ", active" : ""}, ${record.status}`);
  const v = record.validation || {};
  const c = record.conditions || {};
  const rows = [["RMS error", degArc(v.rms_deg)], ["largest error", degArc(v.max_deg)], ["validation points", v.n_points ?? "—"],
    ["compared with", v.compared_with || "—"], ["mean temperature", isNum(c.temp_c_mean) ? `${c.temp_c_mean.toFixed(2)} °C` : "—"],
    ["samples per point", c.samples_per_point ?? "—"], ["created", `${utcDate(record.created_utc)} UTC by ${record.operator || "?"}`]];
  byIdAs("rec-validation", HTMLTableElement).tBodies[0].replaceChildren(...rows.map(([k, x]) => el("tr", {}, el("th", {}, String(k)), el("td", {}, String(x)))));
  void drawJobFigures(record);
  drawBudget(record.budget);
  void drawBudgetHolds(record, opened);
  drawConditions(record);
  drawConformity(record);
  void drawStandards(record);
  byId("rec-approve").onclick = () => decide(id, "approve");
  byId("rec-reject").onclick = () => decide(id, "reject");
  void loadApprovals(id);
  void compareWithPrevious(record);
  const certificate = byIdAs("dl-cert", HTMLButtonElement);
  certificate.disabled = record.status !== "approved";
  certificate.title = record.status === "approved" ? "" : "certificates are issued for approved records only";
  const activate = byIdAs("rec-activate", HTMLButtonElement);
  activate.disabled = record.active;
  setText("rec-msg", message);
  byId("record-detail").dataset.id = String(record.id);
  byId("dl-model").onclick = () => download(`/records/${id}/model`, `record-${id}-MODEL.json`);
  byId("dl-points").onclick = () => download(`/records/${id}/points`, `record-${id}-points.csv`);
  certificate.onclick = () => download(`/records/${id}/certificate`, `record-${id}-certificate.xml`);
  activate.onclick = async () => {
    try {
      await api("POST", `/records/${id}/activate`);
      setText("rec-msg", `record ${id} is now active`);
      await loadRecords();
      await openRecord(id, `record ${id} is now active`);
    } catch (err) {
      setText("rec-msg", operateMessage(err));
    }
  };
  void setupDiagnosis(record, diagnosisId);
  if (record.kind !== "stage") {
    for (const which of ["before", "after"]) {
      byId(`res-${which}`).replaceChildren();
      setText(`res-rms-${which}`, "—");
      delete byId(`res-${which}`).dataset.record;
    }
    setText("res-scale", "(residual maps are drawn for stage records)");
    return;
  }
  try {
    /** @type {import("../types.js").Residuals} */
    const residuals = await api("GET", `/records/${id}/residuals`);
    setText("res-scale", `(${residuals.points.length} points)`);
    setText("res-rms-before", degArc(residuals.rms_before_deg));
    setText("res-rms-after", degArc(residuals.rms_after_deg));
    if (selected !== id) return; // another record was opened meanwhile
    drawResiduals(byId("res-before"), residuals.points, "before");
    drawResiduals(byId("res-after"), residuals.points, "after");
    byId("res-before").dataset.record = byId("res-after").dataset.record = String(id);
  } catch (err) {
    setText("res-scale", `(${errorText(err)})`);
  }
}

export function startRecords() {
  onDiagnosis({
    selected: () => selected,
    download,
    adopted: async (recordId, message) => {
      await loadRecords();
      await openRecord(recordId, message);
    },
    open: async (recordId, diagnosisId) => {
      if (!shared.records.some((r) => r.id === recordId)) await loadRecords();
      await openRecord(recordId, "", diagnosisId ?? null);
    },
  });
}
