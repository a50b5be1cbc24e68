// @ts-check
// What the daemon sends, as the dashboard reads it (the OpenAPI document at /openapi.json is the full
// contract; these are the fields the views use). Types only: this module exports nothing at run time.

/**
 * @typedef {{x_deg?: number | null, y_deg?: number | null}} AxisPair
 * @typedef {{x_deg?: number | null, y_deg?: number | null, moving?: boolean}} StagePose
 */

/**
 * The corrected table tilt of a reading or of GET /tilt. The uncertainties by name are read when the daemon
 * sends them; `u_x_deg`, `u_y_deg`, `k` and `k_y` are their deprecated aliases (expanded uncertainty, factors).
 * @typedef {object} TableTilt
 * @property {number} x_deg
 * @property {number} y_deg
 * @property {number} [expanded_uncertainty_x_deg]
 * @property {number} [expanded_uncertainty_y_deg]
 * @property {number} [standard_uncertainty_x_deg]
 * @property {number} [standard_uncertainty_y_deg]
 * @property {number} [coverage_factor_x]
 * @property {number} [coverage_factor_y]
 * @property {number} [coverage_probability]
 * @property {number} [degrees_of_freedom_x]
 * @property {number} [degrees_of_freedom_y]
 * @property {number} [n_readings]
 * @property {number} [window_s]
 * @property {number} [u_x_deg]
 * @property {number} [u_y_deg]
 * @property {number} [k]
 * @property {number} [k_y]
 */

/**
 * @typedef {object} CalibrationInUse
 * @property {number} record_id
 * @property {number} version
 * @property {string} method
 * @property {string} [status]
 */

/**
 * A message of WS /ws/readings: the snapshot first (with the history asked for), then readings, and
 * `dropped` when the client read too slowly.
 * @typedef {object} ReadingMessage
 * @property {"snapshot" | "reading" | "dropped"} type
 * @property {number} [seq]
 * @property {string} [time_utc]
 * @property {{measurement_sensor?: AxisPair, reference_sensor?: AxisPair}} [raw]
 * @property {TableTilt | null} [table_tilt]
 * @property {StagePose} [stage]
 * @property {number | null} [temp_c]
 * @property {CalibrationInUse | null} [calibration]
 * @property {ReadingMessage[]} [history]
 * @property {string} [bench]
 * @property {number} [rate_hz]
 * @property {number} [count]
 */

/**
 * @typedef {object} Simulated
 * @property {string | null} scenario
 * @property {number} speed
 */

/**
 * @typedef {object} Bench
 * @property {string} name
 * @property {string} kind
 * @property {string} state
 * @property {string | null} held_by
 * @property {Simulated | null} [simulated]
 * @property {string | null} [node]
 * @property {boolean} [online]
 */

/**
 * What the instrument reported itself to be; where it is connected is the device's `port`.
 * @typedef {object} Identity
 * @property {string | null} model
 * @property {string | null} serial
 * @property {string | null} firmware
 * @property {string | null} [address]
 */

/**
 * @typedef {object} Device
 * @property {string} role
 * @property {string | null} port
 * @property {string | null} protocol
 * @property {string} state
 * @property {string | null} last_frame_utc
 * @property {{frames: number, bad_checksum: number, resyncs: number, timeouts: number, reconnects: number}} counters
 * @property {Identity | null} identity
 * @property {string | null} error
 */

/**
 * @typedef {object} ValidationFigures
 * @property {number | null} [rms_deg]
 * @property {number | null} [max_deg]
 * @property {number | null} [n_points]
 * @property {string} [compared_with]
 * @property {number | null} [predicted_expanded_uncertainty_deg] an adaptive job's predicted U of the correction
 * @property {number | null} [validated_expanded_uncertainty_deg]
 * @property {number} [validation_reading_u_deg] the validation readings' own noise (standard uncertainty of a point's mean)
 * @property {number | null} [coverage]
 * @property {{error_deg?: number, u_x_deg?: number, u_y_deg?: number, expanded_uncertainty_x_deg?: number,
 *   expanded_uncertainty_y_deg?: number, measured_x_deg?: number, measured_y_deg?: number, reference_x_deg?: number,
 *   reference_y_deg?: number}[]} [points]
 */

/**
 * A job's bench time (bench seconds: a simulated speed-up does not change them).
 * @typedef {object} BenchSeconds
 * @property {number} total
 * @property {number} [moving]
 * @property {number} [settling]
 * @property {number} [reading]
 */

/**
 * @typedef {object} BudgetContribution
 * @property {string} source
 * @property {string} [name]
 * @property {number} standard_uncertainty
 * @property {number | null} [dof]
 */

/**
 * @typedef {object} BudgetResult
 * @property {string} name
 * @property {string} unit
 * @property {BudgetContribution[]} contributions
 * @property {number} standard_uncertainty u_c
 * @property {number} expanded_uncertainty U = k·u_c
 * @property {number} coverage_factor k
 * @property {number} coverage_probability
 * @property {number | null} [dof_eff]
 * @property {string} [quantity]
 * @property {{expanded_uncertainty: number, coverage_factor?: number, standard_uncertainty?: number} | null} [single_reading] the U of one corrected reading, where the daemon gives it
 */

/**
 * An ambient condition of a job: value with its standard uncertainty, and (from an ambient sensor) its range.
 * @typedef {object} Condition
 * @property {number} value
 * @property {number} standard_uncertainty
 * @property {number} [min]
 * @property {number} [max]
 * @property {number} [n_readings]
 * @property {string} [source]
 */

/**
 * What the record's job ran with, and the laboratory's ambient conditions.
 * @typedef {object} RecordConditions
 * @property {number | null} [temp_c_mean]
 * @property {number | null} [samples_per_point]
 * @property {Condition | null} [ambient_temperature_c]
 * @property {Condition | null} [relative_humidity_pct]
 */

/**
 * A reference standard as a record names it; who calibrated it is the standard's own entry (GET /standards/{id}).
 * @typedef {object} RecordStandard
 * @property {number} id
 * @property {string} name
 * @property {string} [serial]
 * @property {string} [certificate_id]
 * @property {number | null} [expanded_uncertainty_deg]
 * @property {number | null} [coverage_factor]
 */

/**
 * @typedef {object} CalibratedBy
 * @property {string} name
 * @property {string | null} [accreditation]
 * @property {string | null} [city]
 * @property {string} country_code
 */

/**
 * @typedef {object} Standard
 * @property {number} id
 * @property {string} name
 * @property {string} serial
 * @property {string} certificate_number
 * @property {string} calibrated_on
 * @property {string} due_on
 * @property {number | null} [expanded_uncertainty_deg]
 * @property {number | null} [coverage_factor]
 * @property {"valid" | "due_soon" | "past_due"} status
 * @property {CalibratedBy | null} [calibrated_by]
 */

/**
 * The statements of conformity of a record whose order has a specification (as its certificate states them).
 * @typedef {object} Conformity
 * @property {string | null} x
 * @property {string | null} y
 * @property {string} decision_rule
 * @property {number} max_permissible_error_deg
 * @property {number | null} [guard_band_fraction]
 * @property {Record<string, string | null> | null} [parameters]
 * @property {Record<string, number | null>} [largest_probability_of_false_acceptance]
 * @property {Record<string, {error?: number, expanded_uncertainty?: number, unit?: string}>} [worst_point]
 */

/**
 * The record's uncertainty budget.
 * @typedef {object} Budget
 * @property {BudgetResult[]} [results]
 * @property {boolean} [traceable]
 * @property {string} [warning]
 */

/**
 * @typedef {object} CalibratedRange
 * @property {number[]} [x_deg]
 * @property {number[]} [y_deg]
 */

/**
 * @typedef {object} CalibrationRecord
 * @property {number} id
 * @property {number} device_id
 * @property {string} kind
 * @property {number} version
 * @property {string} method
 * @property {string} created_utc
 * @property {string} [operator]
 * @property {string} [status]
 * @property {boolean} active
 * @property {number | null} [supersedes_id]
 * @property {number | null} [job_id]
 * @property {ValidationFigures | null} validation
 * @property {RecordConditions | null} [conditions]
 * @property {Budget | null} [budget]
 * @property {{diagnosis_id?: number, added_effects?: string[], adopted_from_record_id?: number,
 *   measurement_job_ids?: number[], bench_seconds?: BenchSeconds | null}} [raw_data]
 * @property {CalibratedRange | null} [calibrated_range]
 * @property {RecordStandard[] | null} [reference_standards]
 * @property {Conformity | null} [conformity]
 * @property {BenchSeconds | null} [bench_seconds]
 * @property {number | null} [predicted_expanded_uncertainty_deg]
 */

/**
 * @typedef {object} Grid
 * @property {number[]} [x_deg]
 * @property {number[]} [y_deg]
 * @property {number} [n_x]
 * @property {number} [n_y]
 * @property {number[][]} [points]
 */

/**
 * @typedef {object} JobPoint
 * @property {number} index
 * @property {number} x_deg
 * @property {number | null} [y_deg]
 */

/**
 * @typedef {object} Job
 * @property {number} id
 * @property {string} state
 * @property {{points_done: number, points_total: number, phase: string | null}} progress
 * @property {string | null} error
 * @property {{id: number, version: number} | null} record
 * @property {ValidationFigures | null} validation
 * @property {{grid?: Grid | null, design?: string, target_expanded_uncertainty_deg?: number, samples_per_point?: number,
 *   conditions?: object}} request
 * @property {string} [procedure]
 * @property {string} [created_by]
 * @property {BenchSeconds | null} [bench_seconds]
 * @property {number | null} [predicted_expanded_uncertainty_deg]
 */

/**
 * A message of WS /ws/jobs/{id}.
 * @typedef {object} JobMessage
 * @property {"snapshot" | "point" | "job" | "end"} type
 * @property {Job} [job]
 * @property {JobPoint[]} [points]
 * @property {JobPoint} [point]
 */

/**
 * @typedef {object} ResidualPoint
 * @property {number} point
 * @property {string} role
 * @property {number} stage_x_deg
 * @property {number} stage_y_deg
 * @property {number} before_x_deg
 * @property {number} before_y_deg
 * @property {number} after_x_deg
 * @property {number} after_y_deg
 */

/**
 * @typedef {object} Residuals
 * @property {ResidualPoint[]} points
 * @property {number} rms_before_deg
 * @property {number} rms_after_deg
 */

/**
 * Per point diagnosed: stage angles, approach directions and the residual (measured − model) with the baseline
 * alone (before) and with the named effects (after), degrees.
 * @typedef {object} ResidualMaps
 * @property {number[][]} stage_deg
 * @property {number[][]} [approach]
 * @property {number[][]} before_deg
 * @property {number[][]} after_deg
 */

/**
 * Whether the record can adopt a named effect from the points diagnosed, why not, and what would tell.
 * @typedef {object} Adoption
 * @property {string} effect
 * @property {boolean} adoptable
 * @property {string} reason
 * @property {string | null} [measurement]
 */

/**
 * The measurement that would test what the stored points cannot.
 * @typedef {object} MeasurementPlan
 * @property {number} [n_points]
 * @property {{stage_x_deg: number, stage_y_deg: number, dir_x: number, dir_y: number}[]} [points]
 * @property {{effect: string, why?: string, measurement?: string, n_points?: number}[]} [parts]
 * @property {{effect: string, reason: string}[]} [cannot]
 * @property {number | null} [estimated_bench_s]
 * @property {number | null} [seconds_per_point]
 * @property {string} [estimate_source]
 * @property {string} [approach]
 * @property {string} [summary]
 */

/**
 * The answer of POST /records/{id}/diagnose with plan_only.
 * @typedef {object} DiagnosisPlan
 * @property {number} record_id
 * @property {string[]} named_effects
 * @property {{effect: string, reason: string}[]} [untestable]
 * @property {boolean} adoptable
 * @property {Adoption[]} adoption
 * @property {number} n_points
 * @property {MeasurementPlan} plan
 */

/**
 * @typedef {{rms: number, max: number}} Gap
 * @typedef {object} Diagnosis
 * @property {number} id
 * @property {string} state
 * @property {string | null} [phase]
 * @property {string | null} [error]
 * @property {string | null} [conclusion]
 * @property {string[]} named_effects
 * @property {{effect: string, summary: string}[]} effects
 * @property {Gap | null} gap_before_deg
 * @property {Gap | null} gap_after_deg
 * @property {number | null} noise_deg
 * @property {number} [record_id]
 * @property {{effect: string, reason: string}[]} [untestable]
 * @property {boolean | null} [adoptable]
 * @property {Adoption[]} [adoption]
 * @property {MeasurementPlan | null} [measurement_plan]
 * @property {{plan?: MeasurementPlan, job_id?: number, job?: {id: number}} | null} [measurement]
 * @property {ResidualMaps | null} [residual_maps]
 */

/**
 * @typedef {object} LevelResult
 * @property {AxisPair} achieved
 * @property {number} iterations
 * @property {AxisPair} stage
 * @property {boolean} within_tolerance
 */

/**
 * The person behind a token: certificates name them, approving needs a name and a function.
 * @typedef {{name: string, function: string | null}} Person
 */

/**
 * @typedef {object} Token
 * @property {string} name
 * @property {string[]} scopes
 * @property {string} created_utc
 * @property {string} created_by
 * @property {string | null} revoked_utc
 * @property {Person | null} [person]
 */

/**
 * @typedef {Token & {token: string}} CreatedToken
 */

/**
 * A decision on a record (the audit trail of its approvals): the token it was signed with and the person behind it.
 * @typedef {object} Approval
 * @property {number} id
 * @property {"approve" | "reject"} decision
 * @property {string} meaning
 * @property {string | null} note
 * @property {string} actor
 * @property {Person | null} [signer]
 * @property {string} time_utc
 */

export {};
