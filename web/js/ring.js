// @ts-check
// The live readings of the last hour in columns: appends are O(1) amortised, the newest `capacity` rows are
// one contiguous run, and each row knows whether readings are missing before it (a gap the chart must
// not bridge with a line).

/** @typedef {"t" | "tx" | "ty" | "ux" | "uy" | "mx" | "my" | "rx" | "ry"} Column */

/** @type {Column[]} */
export const COLUMNS = ["t", "tx", "ty", "ux", "uy", "mx", "my", "rx", "ry"];

/**
 * One reading as the chart keeps it: time in seconds since the epoch (UTC), table tilt and its expanded
 * uncertainty per axis, and the raw readings of both sensors (NaN where the message had none).
 * @typedef {Record<Column, number>} Row
 */

export class Ring {
  /** @param {number} capacity */
  constructor(capacity) {
    this.capacity = capacity;
    this.len = 0;
    /** @type {Record<Column, Float64Array>} */
    this.cols = /** @type {Record<Column, Float64Array>} */ (Object.fromEntries(COLUMNS.map((name) => [name, new Float64Array(2 * capacity)])));
    this.gapBefore = new Uint8Array(2 * capacity);
  }

  get lastT() {
    return this.len ? this.cols.t[this.len - 1] : -Infinity;
  }

  get size() {
    return Math.min(this.len, this.capacity);
  }

  /** @param {Row} row @param {boolean} gapBefore readings are missing between the previous row and this one */
  push(row, gapBefore) {
    if (this.len === 2 * this.capacity) {
      for (const name of COLUMNS) this.cols[name].copyWithin(0, this.capacity, 2 * this.capacity);
      this.gapBefore.copyWithin(0, this.capacity, 2 * this.capacity);
      this.len = this.capacity;
    }
    for (const name of COLUMNS) this.cols[name][this.len] = row[name];
    this.gapBefore[this.len] = gapBefore ? 1 : 0;
    this.len += 1;
  }

  clear() {
    this.len = 0;
  }

  /** The index of the first row with t >= t0. @param {number} t0 */
  lowerBound(t0) {
    let lo = Math.max(0, this.len - this.capacity);
    let hi = this.len;
    while (lo < hi) {
      const mid = (lo + hi) >> 1;
      if (this.cols.t[mid] < t0) lo = mid + 1;
      else hi = mid;
    }
    return lo;
  }

  /**
   * The gaps in [t0, now]: each from the last reading before it to the first after it.
   * @param {number} t0
   * @returns {{from: number, to: number}[]}
   */
  gaps(t0) {
    const out = [];
    for (let i = Math.max(1, this.lowerBound(t0)); i < this.len; i++) {
      if (this.gapBefore[i]) out.push({ from: this.cols.t[i - 1], to: this.cols.t[i] });
    }
    return out;
  }
}
