// @ts-check
// The daemon's HTTP API: the token (from the address's #token= fragment, kept for the browser session),
// requests with it, and problem+json errors as ApiError with the daemon's own words.

const TOKEN_KEY = "tiltlab-token";

/** The token of this session: taken from the fragment once (and removed from the address bar), else kept. */
function sessionToken() {
  const fragment = new URLSearchParams(location.hash.slice(1));
  const given = fragment.get("token");
  if (given) {
    sessionStorage.setItem(TOKEN_KEY, given);
    history.replaceState(null, "", location.pathname + location.search);
  }
  return sessionStorage.getItem(TOKEN_KEY);
}

export const token = sessionToken();

/** @type {(title: string, detail: string) => void} */
let refused = () => {};

/**
 * What to do when the daemon refuses the token (401) or a read needs a scope it lacks (403).
 * @param {(title: string, detail: string) => void} handler
 */
export function onTokenRefused(handler) {
  refused = handler;
}

/** @param {string} title @param {string} detail */
export function tokenRefused(title, detail) {
  refused(title, detail);
}

export class ApiError extends Error {
  /** @param {number} status @param {string} detail @param {string | null} [field] */
  constructor(status, detail, field = null) {
    super(detail);
    this.status = status;
    this.field = field;
  }
}

/**
 * A request to the daemon; JSON answers parsed, others as a Blob.
 * @template [T=any]
 * @param {string} method
 * @param {string} path
 * @param {unknown} [body]
 * @param {{mayLackScope?: boolean}} [options] mayLackScope: a 403 is this request's answer alone (the page's
 *   token may not have the admin scope this read needs), not a reason to lock the page
 * @returns {Promise<T>}
 */
export async function api(method, path, body, options = {}) {
  /** @type {Record<string, string>} */
  const headers = { Accept: "application/json", Authorization: `Bearer ${token}` };
  if (body !== undefined) headers["Content-Type"] = "application/json";
  let answer;
  try {
    answer = await fetch(path, { method, headers, cache: "no-store", body: body === undefined ? undefined : JSON.stringify(body) });
  } catch (_) {
    throw new ApiError(0, `no answer from the service at ${path}`);
  }
  if (!answer.ok) {
    let detail = answer.statusText;
    let field = null;
    try {
      const problem = await answer.json();
      detail = problem.detail || problem.title || detail;
      field = typeof problem.field === "string" ? problem.field : null;
    } catch (_) { /* not problem+json */ }
    if (answer.status === 401) tokenRefused("The token was not accepted", `${path} answered 401: ${detail}`);
    if (answer.status === 403 && method === "GET" && !options.mayLackScope) tokenRefused("The token lacks a scope this page needs", `${path} answered 403: ${detail}`);
    throw new ApiError(answer.status, `${method} ${path} answered HTTP ${answer.status}: ${detail}`, field);
  }
  const type = answer.headers.get("content-type") || "";
  return /** @type {T} */ (type.includes("json") ? await answer.json() : await answer.blob());
}

/** @param {unknown} err */
export function errorText(err) {
  return err instanceof Error ? err.message : String(err);
}

/** What a refused action says, with the scope it needs when that was the reason. @param {unknown} err */
export function operateMessage(err) {
  const text = errorText(err);
  return err instanceof ApiError && err.status === 403 ? `${text} (this needs a token with the operate scope)` : text;
}

// The token travels as the subprotocol bearer.<token>, never in the URL (URLs end up in logs). Text a
// subprotocol cannot carry goes in the query, so the daemon can say why it was refused.
const SUBPROTOCOL_SAFE = /^[A-Za-z0-9._~-]+$/;

/**
 * @param {string} path
 * @param {Record<string, string>} params
 */
export function wsUrl(path, params) {
  const query = new URLSearchParams(SUBPROTOCOL_SAFE.test(token || "") ? params : { ...params, token: token || "" });
  return `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}${path}?${query}`;
}

export function wsProtocols() {
  return SUBPROTOCOL_SAFE.test(token || "") ? [`bearer.${token}`] : [];
}
