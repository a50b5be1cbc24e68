// @ts-check
// Numbers as the lab reads them: every value with its unit, uncertainties to two significant digits and the
// value to the same decimal place (GUM 7.2.6), times in UTC.

/**
 * @param {unknown} value
 * @returns {value is number}
 */
export const isNum = (value) => typeof value === "number" && Number.isFinite(value);

/** @param {unknown} value @param {number} [decimals] */
export const deg = (value, decimals = 4) => (isNum(value) ? `${value.toFixed(decimals)}°` : "—");

/** @param {unknown} valueDeg @param {number} [decimals] */
export const arcsec = (valueDeg, decimals = 1) => (isNum(valueDeg) ? `${(valueDeg * 3600).toFixed(decimals)}″` : "—");

/** @param {unknown} value */
export const degArc = (value) => (isNum(value) ? `${value.toFixed(5)}° (${(value * 3600).toFixed(1)}″)` : "—");

/**
 * Decimals that show an expanded uncertainty to two significant digits.
 * @param {number | null | undefined} u
 */
export function uDecimals(u) {
  return isNum(u) && u > 0 ? Math.max(0, 1 - Math.floor(Math.log10(u))) : 4;
}

/**
 * @param {number | null | undefined} value
 * @param {number | null | undefined} u
 */
export function gumDeg(value, u) {
  if (!isNum(value)) return "—";
  if (!isNum(u) || !(u > 0)) return `${value.toFixed(4)}°`;
  const decimals = uDecimals(u);
  return `${value.toFixed(decimals)}° ± ${u.toFixed(decimals)}°`;
}

/** A coverage factor to three digits. @param {unknown} k */
export const kText = (k) => (isNum(k) ? k.toPrecision(3) : "—");

/** @param {string | number | null | undefined} t */
export const utcTime = (t) => (t ? new Date(t).toISOString().slice(11, 23) + " UTC" : "—");

/** @param {string | number | null | undefined} t */
export const utcDate = (t) => (t ? new Date(t).toISOString().slice(0, 19).replace("T", " ") : "—");

/**
 * The UTC time of day of a time in seconds since the epoch, with `ms` decimals of the second.
 * @param {number} seconds
 * @param {number} [ms]
 */
export function utcClock(seconds, ms = 0) {
  const text = new Date(seconds * 1e3).toISOString();
  return ms ? text.slice(11, 20 + ms) : text.slice(11, 19);
}

/** @param {string | null | undefined} t @param {boolean} [zone] */
export function ageText(t, zone = true) {
  if (!t) return "never";
  const seconds = (Date.now() - new Date(t).getTime()) / 1000;
  const time = zone ? utcTime(t) : utcTime(t).replace(" UTC", "");
  return `${time} (${Math.max(0, seconds).toFixed(1)} s ago)`;
}

/**
 * An age in words: "0.4 s", "12 s", "3 min 5 s", "2 h 10 min".
 * @param {number} seconds
 */
export function durationText(seconds) {
  if (seconds < 10) return `${Math.max(0, seconds).toFixed(1)} s`;
  if (seconds < 60) return `${Math.round(seconds)} s`;
  if (seconds < 3600) return `${Math.floor(seconds / 60)} min ${Math.round(seconds % 60)} s`;
  return `${Math.floor(seconds / 3600)} h ${Math.round((seconds % 3600) / 60)} min`;
}

/**
 * A length in degrees for a scale bar, in the unit that reads best (°, or ″ below a hundredth of a degree).
 * @param {number} lengthDeg
 */
export function scaleText(lengthDeg) {
  if (lengthDeg >= 0.01) return `${+lengthDeg.toPrecision(2)}°`;
  return `${+(lengthDeg * 3600).toPrecision(2)}″`;
}

/**
 * A person as certificates name them: "Dr. A. Example, Head of Laboratory"; a token without one says so.
 * @param {{name: string, function: string | null} | null | undefined} person
 */
export function personText(person) {
  if (!person) return "no person named";
  return person.function ? `${person.name}, ${person.function}` : `${person.name} (no function given)`;
}

/**
 * A value with its standard uncertainty (k = 1), to the uncertainty's two significant digits.
 * @param {number | null | undefined} value
 * @param {number | null | undefined} u
 * @param {string} unit
 */
export function withStandardU(value, u, unit) {
  if (!isNum(value)) return "—";
  if (!isNum(u) || !(u > 0)) return `${value} ${unit}`;
  const decimals = uDecimals(u);
  return `${value.toFixed(decimals)} ${unit}, u = ${u.toFixed(decimals)} ${unit} (standard uncertainty)`;
}

/** The statements of conformity in words (ILAC-G8, DCC `conformity`). */
export const CONFORMITY_WORDS = /** @type {Record<string, string>} */ ({
  pass: "pass: within the specification",
  fail: "fail: outside the specification",
  conditionalPass: "conditional pass: the error is within the limit, but its uncertainty reaches past it",
  conditionalFail: "conditional fail: the error is past the limit, but within its uncertainty of it",
});

/** @param {string | null | undefined} statement */
export const conformityText = (statement) => (statement ? CONFORMITY_WORDS[statement] || statement : "no statement");

/**
 * A decision rule in words.
 * @param {string} rule
 * @param {number | null | undefined} [guardBandFraction]
 */
export function decisionRuleText(rule, guardBandFraction) {
  if (rule === "simple_acceptance") return "simple acceptance: passes where |error| ≤ MPE (no guard band)";
  if (rule === "guarded_acceptance") {
    const f = isNum(guardBandFraction) ? guardBandFraction : 1;
    return `guarded acceptance: passes where |error| ≤ MPE − w, guard band w = ${f === 1 ? "U" : `${f} U`}`;
  }
  if (rule === "non_binary") return "non-binary: pass where |error| + U ≤ MPE, conditional where the limit lies within ± U of the error";
  return rule;
}

/**
 * A job's bench time in words, or null when the daemon does not give it.
 * @param {{total: number, moving?: number, settling?: number, reading?: number} | null | undefined} b
 */
export function benchSecondsText(b) {
  if (!b || !isNum(b.total)) return null;
  /** @param {number | undefined} x */
  const s = (x) => (isNum(x) ? `${x.toFixed(x < 100 ? 1 : 0)} s` : "—");
  return `${s(b.total)} of bench time: moving ${s(b.moving)}, settling ${s(b.settling)}, reading ${s(b.reading)}`;
}
