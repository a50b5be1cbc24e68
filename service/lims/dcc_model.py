"""What a Digital Calibration Certificate says, in the lab's terms (written as XML by
service.lims.dcc)."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field

REFTYPE_NAMESPACE = "tiltlab"
REFTYPE_LINK = "urn:tiltlab:reftypes"
# Every refType of our own a certificate may use, with what it means (written into the certificate).
REFTYPES = {
    "tiltlab_values": "A list of single quantities of one result (each with its own label).",
    "tiltlab_table": "A table: quantities of equal length, row i of every column belongs to one "
    "point.",
    "tiltlab_modelParameter": "A fitted parameter of the calibration model; its si:label is the "
    "parameter's name in the model file (MODEL.json) of the calibration record.",
    "tiltlab_parameterVector": "The fitted parameters as one vector: values, expanded "
    "uncertainties and their covariance matrix (ordered as the labels), from which any function "
    "of the parameters can be propagated.",
    "tiltlab_calibratedRange": "The lowest and highest value of a quantity at the calibration "
    "points: the range the results hold for.",
    "tiltlab_calibrationPoint": "A column of the calibration points: the points the model was "
    "fitted on.",
    "tiltlab_validationPoint": "A column of the validation points: points measured after the fit, "
    "not used by it.",
    "tiltlab_internalTemperature": "The temperature the instrument's own internal sensor "
    "reported during the measurement (not a calibrated thermometer's reading of the ambient "
    "air).",
    "tiltlab_summary": "A summary figure of a result (RMS or largest error, number of points).",
    "tiltlab_uncertaintyComponent": "One component of an uncertainty budget: a standard "
    "uncertainty (GUM), already multiplied by its sensitivity, in the unit of the result.",
    "tiltlab_uncertaintyCombination": "The combination of an uncertainty budget's components: "
    "the combined standard uncertainty, its effective degrees of freedom, the coverage factor "
    "and the expanded uncertainty.",
    "tiltlab_standardUncertaintyStatement": "The uncertainty of a reference standard as its own "
    "calibration certificate states it: the expanded uncertainty U, its coverage factor k and "
    "coverage probability p, and the standard uncertainty u = U/k that enters the results.",
    "tiltlab_indicationError": "A column of the item's indication errors as found: the item's "
    "reading minus the reference's, at every calibration and validation point, before any "
    "correction.",
    "tiltlab_ambientCondition": "An ambient condition of the laboratory during the calibration "
    "(air temperature, relative humidity), with its standard uncertainty.",
    "tiltlab_conformityStatement": "A statement of conformity (ISO/IEC 17025 7.8.6, ILAC-G8) of "
    "one quantity with the specification of the order: the decision rule, the limit and the "
    "figures the decision rests on.",
}


@dataclass(frozen=True)
class Address:
    city: str
    country_code: str  # ISO 3166-1 alpha-2
    street: str | None = None
    post_code: str | None = None


@dataclass(frozen=True)
class Contact:
    name: str
    address: Address
    email: str | None = None


@dataclass(frozen=True)
class Person:
    name: str
    role: str  # the person's function in the laboratory (e.g. "Head of Laboratory")
    main_signer: bool = False
    statement: str = ""  # e.g. what the person approved, when, and its meaning


@dataclass(frozen=True)
class Identification:
    issuer: str  # manufacturer | calibrationLaboratory | customer | owner | other
    value: str
    name: str


@dataclass(frozen=True)
class Item:
    name: str
    # what identifies the item: its serial, never a port or role
    identifications: tuple[Identification, ...]
    model: str | None = None
    manufacturer: str | None = None
    firmware: str | None = None


@dataclass(frozen=True)
class Method:
    name: str
    description: str
    references: tuple[str, ...] = ()  # the papers the method follows
    procedure: str = ""  # the lab's procedure it runs


@dataclass(frozen=True)
class CalibratingLaboratory:
    """The laboratory that calibrated a reference standard (named on the standard's own
    certificate)."""

    name: str
    country_code: str
    accreditation: str | None = None
    city: str | None = None

    def described(self) -> str:
        where = ", ".join(part for part in (self.city, self.country_code) if part)
        return f"{self.name} ({where})" + (
            f", accreditation {self.accreditation}" if self.accreditation else ""
        )


@dataclass(frozen=True)
class ReferenceStandard:
    name: str
    serial: str
    certificate_number: str
    certificate_sha256: str
    calibrated_on: dt.date
    due_on: dt.date
    uncertainty: str  # the certificate's wording, a remark
    calibrated_by: CalibratingLaboratory | None = None
    expanded_uncertainty: float | None = None  # U of the standard's angle, in `unit`
    coverage_factor: float | None = None
    coverage_probability: float = 0.95
    unit: str = "deg"
    valid_on_performance_date: bool = True  # calibrated_on <= the calibration's date <= due_on
    model: str | None = None


@dataclass(frozen=True)
class Value:
    """One quantity; an uncertainty, when given, is expanded with its coverage factor, probability
    and distribution."""

    label: str
    name: str
    value: float
    unit: str
    expanded_u: float | None = None
    k: float | None = None
    probability: float | None = None
    note: str = ""
    distribution: str | None = None  # "normal", "student-t", "rectangular"
    ref_type: str = "tiltlab_modelParameter"
    # a standard uncertainty (GUM u) where no expanded one is stated
    standard_u: float | None = None


@dataclass(frozen=True)
class Column:
    """One column of a table (a list of values of one quantity), optionally with expanded
    uncertainties."""

    label: str
    name: str
    values: tuple[float, ...]
    unit: str
    expanded_u: tuple[float, ...] | None = None
    k: tuple[float, ...] | None = None
    probability: float | None = None
    ref_type: str | None = None
    distribution: str | None = None


@dataclass(frozen=True)
class Covariance:
    """Parameters as one vector with their covariance: expanded uncertainties beside the full
    matrix."""

    labels: tuple[str, ...]
    values: tuple[float, ...]
    units: tuple[str, ...]
    matrix: tuple[tuple[float, ...], ...]  # in the units' products
    k: tuple[float, ...]  # each parameter's coverage factor
    probability: float
    region_k: float  # the coverage factor of the joint (hyper-ellipsoidal) region
    distribution: str = "student-t"
    note: str = ""


@dataclass(frozen=True)
class Result:
    name: str
    description: str = ""
    values: tuple[Value, ...] = ()
    columns: tuple[Column, ...] = ()
    covariance: Covariance | None = None
    table_ref_type: str = "tiltlab_table"


@dataclass(frozen=True)
class MeasurementResult:
    name: str
    results: tuple[Result, ...]
    description: str = ""


@dataclass(frozen=True)
class Condition:
    """A measurement condition (an influence quantity): one or more values under one name."""

    label: str
    name: str
    values: tuple[Value, ...]
    description: str = ""
    ref_type: str | None = None  # default basic_<label>


@dataclass(frozen=True)
class Statement:
    """A statement of the certificate: a declaration, and for a statement of conformity its outcome
    (the DCC's pass, fail, conditionalPass or conditionalFail) with the figures it rests on."""

    declaration: str
    name: str = ""
    conformity: str | None = None
    norm: str | None = None
    values: tuple[Value, ...] = ()
    ref_type: str | None = None


@dataclass(frozen=True)
class Certificate:
    number: str
    software_name: str
    software_version: str
    begin_on: dt.date
    end_on: dt.date
    issued_on: dt.date
    laboratory: Contact
    customer: Contact
    item: Item
    persons: tuple[Person, ...]
    methods: tuple[Method, ...]
    standards: tuple[ReferenceStandard, ...]
    conditions: tuple[Condition, ...]
    results: tuple[MeasurementResult, ...]
    country_code: str = "DE"
    language: str = "en"
    location: str = "laboratory"
    laboratory_code: str | None = None
    identifications: tuple[Identification, ...] = ()
    replaces: str | None = None  # unique identifier of the certificate this one substitutes
    statements: tuple[str | Statement, ...] = field(default_factory=tuple)
    comment: str = ""
    # SHA-256 of the certificate that signs the file (inside what it signs)
    signing_cert_sha256: str | None = None
