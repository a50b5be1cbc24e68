// @ts-check
// The tiltlab dashboard: live readings, bench and device status, calibration jobs, levelling, the stop
// button, records with their residual maps and diagnoses. Plain ES modules, no build step: one module per
// view (views/), the daemon's API (api.js), reconnecting streams (streams.js) and the charts (charts.js).

import { token, onTokenRefused } from "./api.js";
import { byId, byIdAs } from "./dom.js";
import { stopAll } from "./motion.js";
import { shared } from "./state.js";
import { showProblem } from "./views/banner.js";
import { closeReadings, getCharts, live, markDirty, openReadings, startLive } from "./views/live.js";
import { drawRecords, loadRecords, openRecord, startRecords } from "./views/records.js";
import { closeJobStream, followRunningJob, onJobs, run, startRun } from "./views/run.js";
import { loadBenches, loadTokens, onRecords, refreshStatus, startStatus, stopStatus } from "./views/status.js";

/** @param {string} title @param {string} detail */
function showAuth(title, detail) {
  byId("auth-title").textContent = title;
  byId("auth-detail").textContent = detail;
  byId("auth").hidden = false;
  document.body.classList.add("locked");
  closeReadings();
  closeJobStream();
  stopStatus();
}

/** @param {string} name */
function showView(name) {
  for (const tab of byId("tabs").querySelectorAll("button")) tab.setAttribute("aria-selected", String(tab.dataset.view === name));
  for (const view of document.querySelectorAll(".view")) /** @type {HTMLElement} */ (view).hidden = view.id !== `view-${name}`;
  if (name === "live") markDirty();
  if (name === "records") void loadRecords();
  if (name === "status") void loadTokens();
}

// For the browser's console and the dashboard's browser tests: what the live view received and drew, and
// its charts (uPlot instances). Nothing else of the page is reached this way.
Object.assign(window, { tiltlab: { live, get charts() { return getCharts(); }, run } });

async function start() {
  onTokenRefused(showAuth);
  if (!token) {
    showAuth("No access token", "This page needs a token: the address tiltlab serve prints ends in #token=…");
    return;
  }
  // every control answers from the first moment (a tab clicked while the bench list loads opens it; a form
  // sent then says the list is still loading rather than reloading the page)
  for (const tab of byId("tabs").querySelectorAll("button")) tab.addEventListener("click", () => showView(tab.dataset.view || "live"));
  byIdAs("bench-select", HTMLSelectElement).addEventListener("change", (event) => {
    shared.bench = /** @type {HTMLSelectElement} */ (event.target).value;
    openReadings();
    void refreshStatus();
  });
  byId("stop").addEventListener("click", () => { void stopAll(); });
  startStatus();
  startRun();
  startRecords();
  onRecords(() => { if (!byId("view-records").hidden) drawRecords(); });
  onJobs({
    jobEnded: () => { void loadRecords(); },
    openRecord: (id) => { showView("records"); void openRecord(id); },
  });
  try {
    await loadBenches();
  } catch (err) {
    const status = /** @type {{status?: number}} */ (err).status;
    if (status !== 401 && status !== 403) showProblem(err instanceof Error ? err.message : String(err));
    return;
  }
  if (!shared.bench) {
    showProblem("the daemon runs no bench");
    return;
  }
  document.body.dataset.bench = shared.bench; // the page knows its bench: its actions can be sent
  startLive();
  void refreshStatus();
  void followRunningJob();
}

void start();
