// @ts-check
// The page's banners: a problem of the page as a whole, and a lost stream.

import { byId } from "../dom.js";

/** @param {string} text an empty text hides the banner */
export function showProblem(text) {
  const banner = byId("banner");
  banner.textContent = text;
  banner.hidden = !text;
}

/** @param {string} text an empty text hides the banner */
export function showStreamProblem(text) {
  const banner = byId("stream-banner");
  banner.textContent = text;
  banner.hidden = !text;
}
