// @ts-check
// The live charts (uPlot): the table tilt of each axis on its own chart with its expanded-uncertainty band
// and a scale bar, and the raw readings of both sensors. Readings are thinned to about two per pixel
// column for drawing; missing readings are drawn as gaps, never bridged by a line.

import uPlot from "../vendor/uplot/uPlot.esm.js";
import { isNum, scaleText, utcClock } from "./format.js";

/** @typedef {import("./ring.js").Ring} Ring */
/** @typedef {"present" | "window"} YScale */

export const COLOURS = {
  x: "#1f5fbf", y: "#c0392b", xBand: "#1f5fbf38", yBand: "#c0392b38",
  measX: "#1f5fbf", measY: "#c0392b", refX: "#0f8a7e", refY: "#d4870f",
};
const PRESENT_S = 5; // "around the present value": the span of the last seconds, at least the band's
const MIN_HALF_SPAN_DEG = 1e-5;

/** The plot's size for its box. @param {HTMLElement} box */
function sizeOf(box) {
  const width = Math.max(240, box.clientWidth || 600);
  return { width, height: width < 600 ? 170 : 200 };
}

/** The time axis speaks UTC, 24 h, never the browser's zone. @returns {uPlot.Axis} */
function utcAxis() {
  return {
    label: "time (UTC)", labelSize: 20,
    values: (_u, splits, _axis, _space, increment) => splits.map((t) => (t === null ? "" : utcClock(t, increment < 1 ? 1 : 0))),
  };
}

/** @returns {uPlot.Axis} */
function degAxis() {
  return { size: 80, values: (_u, values) => values.map((v) => (v === null ? "" : `${+v.toPrecision(6)}°`)) };
}

/** A round length near `target` (1, 2 or 5 times a power of ten). @param {number} target */
export function roundLength(target) {
  const power = 10 ** Math.floor(Math.log10(target));
  const unit = target / power;
  return (unit >= 5 ? 5 : unit >= 2 ? 2 : 1) * power;
}

/**
 * Draws a vertical scale bar at the plot's right edge: a round length of about a quarter of the y span.
 * @param {uPlot} u
 */
function drawScaleBar(u) {
  const scale = u.scales.y;
  if (scale.min == null || scale.max == null || !(scale.max > scale.min)) return;
  const length = roundLength((scale.max - scale.min) / 4);
  const { left, top, width, height } = u.bbox;
  const ctx = u.ctx;
  const x = left + width - 14 * devicePixelRatio;
  const y0 = top + height - 10 * devicePixelRatio;
  const y1 = y0 - (length / (scale.max - scale.min)) * height;
  ctx.save();
  ctx.strokeStyle = "#1d232a";
  ctx.lineWidth = 2 * devicePixelRatio;
  ctx.beginPath();
  ctx.moveTo(x, y0); ctx.lineTo(x, y1);
  ctx.moveTo(x - 4 * devicePixelRatio, y0); ctx.lineTo(x + 4 * devicePixelRatio, y0);
  ctx.moveTo(x - 4 * devicePixelRatio, y1); ctx.lineTo(x + 4 * devicePixelRatio, y1);
  ctx.stroke();
  ctx.fillStyle = "#1d232a";
  ctx.font = `${12 * devicePixelRatio}px system-ui, sans-serif`;
  ctx.textAlign = "right";
  ctx.textBaseline = "middle";
  ctx.fillText(scaleText(length), x - 6 * devicePixelRatio, (y0 + y1) / 2);
  ctx.restore();
  u.root.dataset.scaleBarDeg = String(length);
}

/**
 * Thinned columns of the rows from t0 on, with a row of nulls wherever readings are missing (uPlot draws
 * a null as a gap). NaN (no value in that reading) is a gap too.
 * @param {Ring} ring
 * @param {number} t0
 * @param {number} maxPoints
 * @param {import("./ring.js").Column[]} columns
 * @returns {{t: number[], series: (number | null)[][], drawn: number}}
 */
export function windowColumns(ring, t0, maxPoints, columns) {
  const i0 = ring.lowerBound(t0);
  const n = ring.len - i0;
  const step = Math.max(1, Math.ceil(n / maxPoints));
  /** @type {number[]} */
  const t = [];
  /** @type {(number | null)[][]} */
  const series = columns.map(() => []);
  const cols = columns.map((name) => ring.cols[name]);
  let previous = i0;
  for (let i = i0; i < ring.len; i += step) {
    let gap = false;
    for (let j = Math.max(previous + 1, i0 + 1); j <= i && !gap; j++) gap = ring.gapBefore[j] === 1;
    if (gap && t.length) {
      t.push((ring.cols.t[i - 1] + ring.cols.t[i]) / 2);
      for (const s of series) s.push(null);
    }
    t.push(ring.cols.t[i]);
    cols.forEach((col, k) => { const v = col[i]; series[k].push(Number.isFinite(v) ? v : null); });
    previous = i;
  }
  return { t, series, drawn: n };
}

/**
 * The y range of a tilt chart. "present": centred on the newest value, as wide as the last seconds'
 * readings and at least four expanded uncertainties each way, so a settling table and its band show;
 * "window": every value and band in the window.
 * @param {number[]} t @param {(number | null)[]} value @param {(number | null)[]} u @param {YScale} mode
 * @returns {[number, number]}
 */
export function tiltRange(t, value, u, mode) {
  let last = -1;
  for (let i = value.length - 1; i >= 0; i--) if (value[i] !== null) { last = i; break; }
  if (last < 0) return [-1, 1];
  const present = /** @type {number} */ (value[last]);
  const uNow = u[last] ?? 0;
  if (mode === "window") {
    let lo = Infinity, hi = -Infinity;
    value.forEach((v, i) => { if (v !== null) { const w = u[i] ?? 0; lo = Math.min(lo, v - w); hi = Math.max(hi, v + w); } });
    const pad = Math.max((hi - lo) * 0.08, MIN_HALF_SPAN_DEG);
    return [lo - pad, hi + pad];
  }
  let half = Math.max(4 * uNow, MIN_HALF_SPAN_DEG);
  for (let i = last; i >= 0 && t[last] - t[i] <= PRESENT_S; i--) {
    const v = value[i];
    if (v !== null) half = Math.max(half, 1.2 * (Math.abs(v - present) + (u[i] ?? 0)));
  }
  return [present - half, present + half];
}

export class LiveCharts {
  /**
   * @param {{tiltX: HTMLElement, tiltY: HTMLElement, raw: HTMLElement}} boxes
   */
  constructor(boxes) {
    this.boxes = boxes;
    /** @type {YScale} */
    this.yScale = "present";
    /** @type {Record<"x" | "y", [number, number]>} */
    this.ranges = { x: [-1, 1], y: [-1, 1] };
    /** @type {[number, number]} */
    this.timeRange = [0, 1];
    this.tiltX = this.tiltChart(boxes.tiltX, "x");
    this.tiltY = this.tiltChart(boxes.tiltY, "y");
    this.raw = this.rawChart(boxes.raw);
  }

  /** @param {HTMLElement} box @param {"x" | "y"} axis */
  tiltChart(box, axis) {
    const colour = COLOURS[axis], band = axis === "x" ? COLOURS.xBand : COLOURS.yBand;
    const name = axis.toUpperCase();
    /** @type {uPlot.Series} */
    const bound = { stroke: band, width: 0, points: { show: false }, class: "band-edge" };
    /** @type {uPlot.Options} */
    const opts = {
      ...sizeOf(box),
      scales: { x: { time: true, range: () => this.timeRange }, y: { auto: true, range: () => this.ranges[axis] } },
      tzDate: (t) => uPlot.tzDate(new Date(t * 1e3), "Etc/UTC"),
      axes: [utcAxis(), degAxis()],
      // two legend entries, as drawn: the line of the reading, and the band's fill for U
      legend: {
        live: true,
        markers: { stroke: (_u, i) => (i === 1 ? colour : band), fill: (_u, i) => (i === 1 ? "transparent" : band), width: 2 },
      },
      cursor: { drag: { x: false, y: false } },
      series: [
        { label: "time (UTC)", value: (_u, t) => (isNum(t) ? utcClock(t, 3) : "—") },
        { label: `table tilt ${name}`, stroke: colour, width: 1.5, points: { show: false }, spanGaps: false,
          value: (_u, v) => (isNum(v) ? `${v.toFixed(5)}°` : "—") },
        { ...bound, label: "reading − U" },
        // the upper bound stands for the band in the legend: its value there is U itself
        { ...bound, class: "band-key", label: "expanded uncertainty U (95 %)",
          value: (u, _v, _s, i) => {
            const hi = i === null ? null : u.data[3][i], mid = i === null ? null : u.data[1][i];
            return isNum(hi) && isNum(mid) ? `${(hi - mid).toPrecision(2)}°` : "—";
          } },
      ],
      // the band between reading − U and reading + U is filled by `bands` alone (the bounds draw no line)
      bands: [{ series: [3, 2], fill: band }],
      hooks: { draw: [drawScaleBar] },
    };
    return new uPlot(opts, [[], [], [], []], box);
  }

  /** @param {HTMLElement} box */
  rawChart(box) {
    /** @param {string} label @param {string} stroke @param {number[]} [dash] @returns {uPlot.Series} */
    const line = (label, stroke, dash) => ({ label, stroke, width: 1.3, points: { show: false }, spanGaps: false, ...(dash ? { dash } : {}) });
    /** @type {uPlot.Options} */
    const opts = {
      ...sizeOf(box),
      scales: { x: { time: true, range: () => this.timeRange }, y: { auto: true } },
      tzDate: (t) => uPlot.tzDate(new Date(t * 1e3), "Etc/UTC"),
      axes: [utcAxis(), degAxis()],
      // each legend entry as its line is drawn: its colour, and dashed where the line is
      legend: { live: true, markers: { dash: (u, i) => (u.series[i].dash ? "dashed" : "solid"), width: 3 } },
      cursor: { drag: { x: false, y: false } },
      series: [
        { label: "time (UTC)", value: (_u, t) => (isNum(t) ? utcClock(t, 3) : "—") },
        line("measurement X", COLOURS.measX), line("measurement Y", COLOURS.measY),
        line("reference X", COLOURS.refX, [6, 4]), line("reference Y", COLOURS.refY, [6, 4]),
      ],
    };
    return new uPlot(opts, [[], [], [], [], []], box);
  }

  resize() {
    this.tiltX.setSize(sizeOf(this.boxes.tiltX));
    this.tiltY.setSize(sizeOf(this.boxes.tiltY));
    this.raw.setSize(sizeOf(this.boxes.raw));
  }

  /**
   * Redraw from the ring: the last `windowS` seconds up to its newest reading.
   * @param {Ring} ring @param {number} windowS
   */
  draw(ring, windowS) {
    const end = ring.lastT;
    const t0 = end - windowS;
    this.timeRange = [t0, end];
    const maxPoints = 2 * Math.max(this.boxes.raw.clientWidth, 300);
    const tilt = windowColumns(ring, t0, maxPoints, ["tx", "ty", "ux", "uy"]);
    const [tx, ty, ux, uy] = tilt.series;
    this.ranges = { x: tiltRange(tilt.t, tx, ux, this.yScale), y: tiltRange(tilt.t, ty, uy, this.yScale) };
    /** @param {(number | null)[]} v @param {(number | null)[]} u @param {number} sign */
    const edge = (v, u, sign) => v.map((value, i) => (value === null || u[i] === null ? null : value + sign * /** @type {number} */ (u[i])));
    this.tiltX.setData([tilt.t, tx, edge(tx, ux, -1), edge(tx, ux, 1)]);
    this.tiltY.setData([tilt.t, ty, edge(ty, uy, -1), edge(ty, uy, 1)]);
    const raw = windowColumns(ring, t0, maxPoints, ["mx", "my", "rx", "ry"]);
    this.raw.setData([raw.t, ...raw.series]);
    for (const box of [this.boxes.tiltX, this.boxes.tiltY, this.boxes.raw]) box.dataset.points = String(raw.drawn);
    return { hasTilt: tx.some((v) => v !== null) };
  }
}
