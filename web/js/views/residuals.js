// @ts-check
// A record's residual map: an arrow at each stage point, scaled so that the longest spans a quarter of the
// grid's half-width, coloured by magnitude; labels and the colour scale outside the frame.

import { svgEl } from "../dom.js";
import { arcsec } from "../format.js";

/** @typedef {import("../types.js").ResidualPoint} ResidualPoint */

// points at most 80 units from the centre, the longest arrow 20 units long: every arrow stays inside the frame (±110)
const MAP_R = 80, MAP_ARROW = 20, MAP_FRAME = 110;

/** 0 green .. 1 red. @param {number} fraction */
function colour(fraction) {
  const hue = 120 * (1 - Math.min(1, Math.max(0, fraction)));
  return `hsl(${hue.toFixed(0)} 70% 42%)`;
}

/**
 * @param {SVGElement | HTMLElement} svg
 * @param {ResidualPoint[]} points
 * @param {"before" | "after"} which
 * @param {number} [scaleDeg] the residual the arrow scale stands for, shared by maps drawn side by side (else
 *   this map's longest arrow)
 */
export function drawResiduals(svg, points, which, scaleDeg) {
  svg.replaceChildren();
  /** @param {ResidualPoint} p */
  const dx = (p) => (which === "before" ? p.before_x_deg : p.after_x_deg);
  /** @param {ResidualPoint} p */
  const dy = (p) => (which === "before" ? p.before_y_deg : p.after_y_deg);
  const span = Math.max(1e-9, ...points.map((p) => Math.max(Math.abs(p.stage_x_deg), Math.abs(p.stage_y_deg))));
  const magnitude = points.map((p) => Math.hypot(dx(p), dy(p)));
  const longest = scaleDeg && scaleDeg > 0 ? scaleDeg : Math.max(1e-12, ...magnitude);
  /** @param {number} x */ const sx = (x) => (MAP_R * x) / span;
  /** @param {number} y */ const sy = (y) => (-MAP_R * y) / span;
  const gain = MAP_ARROW / longest; // map units per degree of residual
  const F = MAP_FRAME;
  const gradientId = `scale-${svg.id}`;
  const gradient = svgEl("linearGradient", { id: gradientId, x1: 0, y1: 1, x2: 0, y2: 0 });
  for (const f of [0, 0.25, 0.5, 0.75, 1]) gradient.append(svgEl("stop", { offset: f, "stop-color": colour(f) }));
  const defs = svgEl("defs", {});
  defs.append(gradient);
  svg.append(defs);
  svg.append(svgEl("rect", { x: -F, y: -F, width: 2 * F, height: 2 * F, class: "frame" }));
  svg.append(svgEl("line", { x1: -F, y1: 0, x2: F, y2: 0, class: "axis" }), svgEl("line", { x1: 0, y1: -F, x2: 0, y2: F, class: "axis" }));
  svg.append(svgEl("text", { x: 0, y: F + 11, class: "tick x-label", "text-anchor": "middle" }, `stage X / ° (edge points ±${+span.toPrecision(3)}°)`));
  svg.append(svgEl("text", { x: -F - 5, y: 0, class: "tick y-label", "text-anchor": "middle", transform: `rotate(-90 ${-F - 5} 0)` },
    `stage Y / ° (edge points ±${+span.toPrecision(3)}°)`));
  // the arrow scale under the frame: a bar as long as the longest arrow, its length in arc seconds
  svg.append(svgEl("line", { x1: -F, y1: F + 24, x2: -F + MAP_ARROW, y2: F + 24, stroke: "#1d232a", "stroke-width": 2, class: "arrow-scale" }));
  svg.append(svgEl("text", { x: -F + MAP_ARROW + 4, y: F + 27, class: "res-label longest" },
    scaleDeg ? `bar ${arcsec(longest, 1)} (both maps)` : `longest arrow ${arcsec(longest, 1)}`));
  // the colour scale at the right of the frame: 0 at the bottom, the longest arrow at the top
  const cx = F + 6;
  svg.append(svgEl("rect", { x: cx, y: -F, width: 7, height: 2 * F, fill: `url(#${gradientId})`, class: "colour-scale" }));
  svg.append(svgEl("text", { x: cx + 10, y: -F + 7, class: "tick" }, arcsec(longest, 1)));
  svg.append(svgEl("text", { x: cx + 10, y: F, class: "tick" }, "0″"));
  points.forEach((p, i) => {
    const x0 = sx(p.stage_x_deg), y0 = sy(p.stage_y_deg);
    const x1 = x0 + gain * dx(p), y1 = y0 - gain * dy(p);
    const c = colour(magnitude[i] / longest);
    const group = svgEl("g", { class: `res ${p.role}`, "data-point": p.point });
    group.append(svgEl("title", {}, `point ${p.point} (${p.role}): ${which} ${arcsec(dx(p), 2)} in X, ${arcsec(dy(p), 2)} in Y`));
    group.append(svgEl("circle", { cx: x0.toFixed(2), cy: y0.toFixed(2), r: 3, fill: p.role === "fit" || p.role === "below" ? c : "#fff", stroke: c }));
    group.append(svgEl("line", { x1: x0.toFixed(2), y1: y0.toFixed(2), x2: x1.toFixed(2), y2: y1.toFixed(2), stroke: c, "stroke-width": 2 }));
    const angle = Math.atan2(y1 - y0, x1 - x0), head = 6;
    if (Math.hypot(x1 - x0, y1 - y0) > 2) {
      const corners = [[x1, y1], [x1 - head * Math.cos(angle - 0.4), y1 - head * Math.sin(angle - 0.4)],
        [x1 - head * Math.cos(angle + 0.4), y1 - head * Math.sin(angle + 0.4)]];
      group.append(svgEl("polygon", { fill: c, points: corners.map((q) => q.map((v) => v.toFixed(2)).join(",")).join(" ") }));
    }
    svg.append(group);
  });
  svg.dataset.points = String(points.length);
}
