"""The facts a certificate's content reads, as storage gathers them: the calibration record (with
its MODEL.json, validation and conditions), the device, the order and its customer, the reference
standards and the calibration points. JSON-shaped, the same objects storage and the API hold: these
types name the keys the content reads (a stored document may carry more)."""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping
from typing import NotRequired, TypedDict

from service.calibration.budget import UncertaintyBudget

__all__ = [
    "AmbientCondition",
    "CalibrationPoint",
    "CalibratingLab",
    "CustomerFacts",
    "DeviceFacts",
    "ModelCovariance",
    "ModelDocument",
    "ModelParameter",
    "ModelState",
    "OrderFacts",
    "RecordConditions",
    "RecordFacts",
    "StandardFacts",
    "StatedRange",
    "Validation",
    "ValidationPoint",
]


class ModelParameter(TypedDict):
    """One parameter of MODEL.json: its value in `unit`; `fixed` when held, not fitted."""

    value: float
    unit: str
    fixed: NotRequired[bool]
    note: NotRequired[str]


class ModelCovariance(TypedDict):
    """MODEL.json's covariance of the fitted parameters: the names in the order of the matrix's
    rows and columns (a non-finite entry is null)."""

    names: list[str]
    matrix: list[list[float | None]]


class ModelState(TypedDict, total=False):
    """What the certificate reads of a model's method-specific state: the parameters that describe
    the bench, not the item."""

    chain_parameters: list[str]


class ModelDocument(TypedDict, total=False):
    """MODEL.json as the certificate reads it: the parameters, their covariance (null without one)
    and the method's state; the degrees of freedom are read wherever the model states them."""

    parameters: dict[str, ModelParameter]
    covariance: ModelCovariance | None
    state: ModelState


# One validation point: `reference_<q>_<unit>`, `measured_<q>_<unit>`, optionally `u_<q>_<unit>`
# (expanded uncertainty) and `k_<q>` or `k`, besides the point's number and its error; all numbers.
ValidationPoint = dict[str, float]


class Validation(TypedDict, total=False):
    """A record's validation on points not used in the fit: its summary (RMS and largest |error| in
    degrees, null without points), the coverage probability and k of the points' U where stated,
    and the points."""

    n_points: int
    rms_deg: float | None
    max_deg: float | None
    compared_with: str
    coverage_probability: float
    k: float
    points: list[ValidationPoint]


class AmbientCondition(TypedDict):
    """An ambient condition of the laboratory as the record keeps it: its value (a mean where the
    bench's sensor read it, with the range and count), its standard uncertainty and where it came
    from (`ambient_sensor` or `request`)."""

    value: float
    standard_uncertainty: NotRequired[float | None]
    source: NotRequired[str]
    min: NotRequired[float]
    max: NotRequired[float]
    n_readings: NotRequired[int]


class RecordConditions(TypedDict, total=False):
    """The conditions a record was measured under, as far as the certificate reads them: the
    ambient air, the sensors' resolutions (degrees per role), readings per point, and the
    instruments' firmware (per role, or one string in older records)."""

    ambient_temperature_c: AmbientCondition
    relative_humidity_pct: AmbientCondition
    resolution_deg: dict[str, float | None]
    samples_per_point: int
    firmware: dict[str, str | None] | str | None


# The calibrated range a record states: per `<quantity>_<unit>` its [lowest, highest]; read where
# it has the form, anything else ignored.
StatedRange = Mapping[str, object]


class RecordFacts(TypedDict):
    """A calibration record as the certificate reads it (the API's view of it). `budget` as stored:
    the content reads it under its present names (`current_names`)."""

    id: int
    version: int
    kind: str
    method: str
    model: ModelDocument
    validation: Validation
    temp_c: float | None
    content_sha256: str
    created_at: dt.datetime
    budget: NotRequired[UncertaintyBudget | None]
    calibrated_range: NotRequired[StatedRange | None]
    conditions: NotRequired[RecordConditions]


class DeviceFacts(TypedDict):
    """The calibrated device: its laboratory id, and model and serial as registered (the
    instrument's own only where it reports firmware, i.e. answers an identification)."""

    id: NotRequired[int]
    model: str
    serial: str
    firmware: str | None
    manufacturer: NotRequired[str | None]


class CustomerFacts(TypedDict):
    """The customer an order names, with its address."""

    name: str
    city: str
    country_code: str
    street: NotRequired[str | None]
    post_code: NotRequired[str | None]
    email: NotRequired[str | None]


class OrderFacts(TypedDict):
    """What the certificate reads of a LIMS order: its id, the item as the customer states it, and
    the customer."""

    lims_order_id: str
    item_serial: str | None
    customer: CustomerFacts
    item_manufacturer: NotRequired[str | None]
    item_model: NotRequired[str | None]


class CalibratingLab(TypedDict):
    """The laboratory that calibrated a reference standard."""

    name: str
    country_code: str
    accreditation: NotRequired[str | None]
    city: NotRequired[str | None]


class StandardFacts(TypedDict):
    """A registered reference standard as the certificate names it: its certificate (number, hash,
    dates, uncertainty in words and, where stated, as a number in degrees with k) and who calibrated
    it. Dates as stored, or ISO text."""

    name: str
    serial: str
    model: NotRequired[str | None]
    certificate_number: str
    certificate_sha256: str
    calibrated_on: dt.date | str
    due_on: dt.date | str
    uncertainty: NotRequired[str]
    expanded_uncertainty_deg: NotRequired[float | None]
    coverage_factor: NotRequired[float | None]
    calibrated_by: NotRequired[CalibratingLab | None]


# A fit point of a kind other than stage: `<quantity>_<unit>` -> its value (the commanded angle).
CalibrationPoint = Mapping[str, float]
