// @ts-check
// The Status view: every bench of the daemon (or the fleet) and every device of the bench shown, polled;
// the bench pill in the header; and a token for a LIMS (admin).

import { api, ApiError, errorText } from "../api.js";
import { byId, byIdAs, el, setText, textField } from "../dom.js";
import { ageText, personText, utcDate, utcTime } from "../format.js";
import { action, setMoving } from "../motion.js";
import { identityText, ROLE_OF_KIND, roleWords, shared } from "../state.js";
import { showProblem } from "./banner.js";

/** @typedef {import("../types.js").Bench} Bench */

const STATUS_POLL_MS = 2000;
/** @type {number | undefined} */
let timer;
/** @type {() => void} */
let recordsChanged = () => {};

/** @param {() => void} handler called when the poll brought the bench's records */
export function onRecords(handler) {
  recordsChanged = handler;
}

/**
 * A bench in the selector: its name, and in a fleet (benches on more than one node) its node and whether
 * that node is offline.
 * @param {Bench} bench @param {Bench[]} benches
 */
function benchLabel(bench, benches) {
  if (!bench.node || new Set(benches.map((b) => b.node)).size < 2) return bench.name;
  return `${bench.name} · ${bench.node}${bench.online === false ? " (offline)" : ""}`;
}

export async function loadBenches() {
  /** @type {{benches: Bench[]}} */
  const answer = await api("GET", "/benches");
  shared.benches = answer.benches;
  const select = byIdAs("bench-select", HTMLSelectElement);
  if (!select.options.length) {
    for (const bench of answer.benches) select.append(el("option", { value: bench.name }, benchLabel(bench, answer.benches)));
    const first = answer.benches.find((b) => b.kind === "stage") || answer.benches[0];
    shared.bench = first ? first.name : null;
    select.value = shared.bench || "";
  }
}

/** The header's bench pill: the bench's state, or that the daemon does not answer. @param {Bench | undefined} bench */
function showBenchState(bench, answered = true) {
  const pill = byId("bench-state");
  pill.textContent = !answered ? "no answer from the daemon" : bench ? `${bench.state}${bench.held_by ? `: ${bench.held_by}` : ""}` : "?";
  pill.className = `pill ${!answered ? "degraded" : bench ? bench.state : ""}`;
}

export async function refreshStatus() {
  clearTimeout(timer);
  const bench = encodeURIComponent(shared.bench || "");
  try {
    // the bench list first: in a fleet another node's bench may not answer, and the list says why
    /** @type {Promise<{devices: import("../types.js").Device[]}>} */
    const devicesAsked = api("GET", `/devices?bench=${bench}`);
    /** @type {Promise<{records: import("../types.js").CalibrationRecord[]}>} */
    const recordsAsked = api("GET", `/records?bench=${bench}`);
    devicesAsked.catch(() => {});
    recordsAsked.catch(() => {});
    /** @type {{benches: Bench[]}} */
    const answer = await api("GET", "/benches");
    shared.benches = answer.benches;
    for (const option of byIdAs("bench-select", HTMLSelectElement).options) { // a fleet's benches come and go
      const known = answer.benches.find((b) => b.name === option.value);
      if (known) option.textContent = benchLabel(known, answer.benches);
    }
    const me = answer.benches.find((b) => b.name === shared.bench);
    showBenchState(me);
    setMoving("bench", !!(me && me.held_by));
    drawBenches(answer.benches);
    const [devices, records] = await Promise.all([devicesAsked, recordsAsked]);
    shared.devices = devices.devices;
    shared.records = records.records;
    drawDevices();
    setText("devices-updated", `at ${utcTime(new Date().toISOString())}`);
    recordsChanged();
    showProblem("");
  } catch (err) {
    if (!(err instanceof ApiError && (err.status === 401 || err.status === 403))) showProblem(errorText(err));
    if (err instanceof ApiError && err.status === 0) showBenchState(undefined, false);
  }
  if (byId("auth").hidden) timer = window.setTimeout(refreshStatus, STATUS_POLL_MS);
}

export function stopStatus() {
  clearTimeout(timer);
}

/** @param {Bench[]} benches */
function drawBenches(benches) {
  byIdAs("benches", HTMLTableElement).tBodies[0].replaceChildren(...benches.map((b) => el("tr", { "data-bench": b.name },
    el("td", {}, b.name), el("td", {}, b.node ? `${b.node}${b.online === false ? " (offline)" : ""}` : "—"), el("td", {}, b.kind),
    el("td", { class: `st-${b.state}` }, b.state), el("td", {}, b.held_by || "—"),
    el("td", {}, b.simulated ? `${b.simulated.scenario || "yes"}, ${b.simulated.speed}× speed` : "no"))));
}

function drawDevices() {
  /** @type {Record<string, import("../types.js").CalibrationRecord>} */
  const active = {};
  for (const record of shared.records) if (record.active) active[ROLE_OF_KIND[record.kind]] = record;
  byIdAs("devices", HTMLTableElement).tBodies[0].replaceChildren(...shared.devices.map((d) => {
    const c = d.counters, used = active[d.role];
    return el("tr", { "data-role": d.role },
      el("td", {}, roleWords(d.role)), el("td", { class: "identity" }, identityText(d.identity)),
      el("td", { class: "port" }, d.port || "—"), el("td", {}, d.protocol || "—"),
      el("td", { class: `st-${d.state}` }, d.state), el("td", {}, ageText(d.last_frame_utc, false)),
      el("td", {}, `${c.frames}`), el("td", {}, `${c.bad_checksum} / ${c.resyncs} / ${c.timeouts} / ${c.reconnects}`),
      el("td", {}, used ? `record ${used.id} v${used.version} (${used.method})` : "none"), el("td", { class: "wrap" }, d.error || "—"));
  }));
}

/** The person fields of a form, or null when the name is left empty (a program's token). @param {FormData} form */
function personOf(form) {
  const name = textField(form, "person_name").trim();
  const role = textField(form, "person_function").trim();
  return name ? { name, function: role || null } : null;
}

/** @param {unknown} err */
function adminMessage(err, what = "this") {
  return err instanceof ApiError && err.status === 403 ? `${err.message} (${what} needs a token with the admin scope)` : errorText(err);
}

/** @param {SubmitEvent} event */
async function makeToken(event) {
  event.preventDefault();
  const form = new FormData(byIdAs("token-form", HTMLFormElement));
  const out = byId("token-result");
  out.className = "";
  out.textContent = "making the token…";
  const person = personOf(form);
  try {
    /** @type {import("../types.js").CreatedToken} */
    const made = await action(byIdAs("token-make", HTMLButtonElement),
      () => api("POST", "/tokens", { name: textField(form, "name"), scopes: [textField(form, "scope")], ...(person ? { person } : {}) }));
    out.replaceChildren(`token ${made.name} (${made.scopes.join(", ")}) ${made.person ? `of ${personText(made.person)}` : "of a program (no person)"}: `,
      el("code", { id: "token-text" }, made.token), " (shown this once)");
    out.className = "ok";
    void loadTokens();
  } catch (err) {
    out.textContent = adminMessage(err, "making tokens");
    out.className = "error";
  }
}

/** @param {SubmitEvent} event */
async function setPerson(event) {
  event.preventDefault();
  const form = new FormData(byIdAs("person-form", HTMLFormElement));
  const out = byId("person-result");
  const name = textField(form, "token_name");
  out.className = "";
  try {
    /** @type {import("../types.js").Token} */
    const changed = await action(byIdAs("person-set", HTMLButtonElement),
      () => api("PATCH", `/tokens/${encodeURIComponent(name)}`, { person: personOf(form) }));
    out.textContent = `token ${changed.name} now belongs to ${personText(changed.person)}`;
    out.className = "ok";
    void loadTokens();
  } catch (err) {
    out.textContent = adminMessage(err, "setting a token's person");
    out.className = "error";
  }
}

/** The active tokens with the person behind each (GET /tokens: admin; a token without the scope is told so). */
export async function loadTokens() {
  const note = byId("tokens-note");
  try {
    /** @type {{tokens: import("../types.js").Token[]}} */
    const answer = await api("GET", "/tokens?limit=200", undefined, { mayLackScope: true });
    byIdAs("tokens", HTMLTableElement).tBodies[0].replaceChildren(...answer.tokens.map((t) => el("tr", { "data-token": t.name },
      el("td", {}, t.name), el("td", {}, t.scopes.join(", ")),
      el("td", { class: t.person ? "person" : "person muted" }, personText(t.person)),
      el("td", {}, utcDate(t.created_utc)), el("td", {}, t.created_by))));
    note.textContent = `(${answer.tokens.length} active)`;
  } catch (err) {
    byIdAs("tokens", HTMLTableElement).tBodies[0].replaceChildren();
    note.textContent = `(${adminMessage(err, "listing tokens")})`;
  }
}

export function startStatus() {
  byIdAs("token-form", HTMLFormElement).addEventListener("submit", makeToken);
  byIdAs("person-form", HTMLFormElement).addEventListener("submit", setPerson);
}
