// @ts-check
// What the views share: the bench shown, the daemon's benches, devices and records as last read.

/** @typedef {import("./types.js").Bench} Bench */
/** @typedef {import("./types.js").Device} Device */
/** @typedef {import("./types.js").CalibrationRecord} CalibrationRecord */

export const shared = {
  /** @type {string | null} */
  bench: null,
  /** @type {Bench[]} */
  benches: [],
  /** @type {Device[]} */
  devices: [],
  /** @type {CalibrationRecord[]} */
  records: [],
};

/** The record kinds and the role of the instrument each calibrates. */
export const ROLE_OF_KIND = /** @type {Record<string, string>} */ ({
  stage: "measurement_sensor", scale: "adc_sensor", rotation: "triaxial_sensor", turntable: "turntable_sensor",
});

/** @param {string} role */
export const roleWords = (role) => role.replace(/_/g, " ");

/**
 * What an instrument reported itself to be, in words: model, serial number (or that it has none, with the
 * bus address it answers at) and firmware. Where it is connected is said apart (the port).
 * @param {import("./types.js").Identity | null | undefined} identity
 */
export function identityText(identity) {
  if (!identity) return "—";
  const serial = identity.serial ? `s/n ${identity.serial}` : `no serial number${identity.address ? ` (bus address ${identity.address})` : ""}`;
  return [identity.model || "unknown model", serial, identity.firmware ? `firmware ${identity.firmware}` : ""].filter(Boolean).join(", ");
}
