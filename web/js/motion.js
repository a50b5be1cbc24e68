// @ts-check
// The stop button: shown while anything may move the stage (the stream says the stage moves, the bench is
// held, an action is under way, a job runs); one click stops whatever moves.

import { api, errorText } from "./api.js";
import { byId, setText } from "./dom.js";
import { shared } from "./state.js";
import { showProblem } from "./views/banner.js";

/** @type {Record<string, boolean>} */
const movingBy = {};
let actionsInFlight = 0;

/** @param {string} source @param {boolean} on */
export function setMoving(source, on) {
  movingBy[source] = on;
  byId("stop").hidden = !(Object.values(movingBy).some(Boolean) || actionsInFlight > 0);
}

/**
 * Runs an action the operator started (a move, a job's start): its button disabled, the stop button shown.
 * @template T
 * @param {HTMLButtonElement} button
 * @param {() => Promise<T>} work
 * @returns {Promise<T>}
 */
export async function action(button, work) {
  actionsInFlight += 1;
  setMoving("action", true);
  button.disabled = true;
  try {
    return await work();
  } finally {
    button.disabled = false;
    actionsInFlight -= 1;
    setMoving("action", false);
  }
}

export async function stopAll() {
  try {
    /** @type {{failed_job?: number | null}} */
    const out = await api("POST", "/stage/stop", { bench: shared.bench });
    setText("move-result", `stopped${out.failed_job ? `; job ${out.failed_job} failed` : ""}`);
    byId("stop").dataset.stopped = "1";
  } catch (err) {
    showProblem(errorText(err));
  }
}
