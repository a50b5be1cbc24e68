"""Bodies of the LIMS routes: reference standards, approvals, orders, the feed and webhooks."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Literal
from urllib.parse import urlsplit

from pydantic import ConfigDict, Field, ValidationInfo, field_validator

from service.api.models.base import Answer
from service.api.models.calibrations import JobState
from service.api.models.records import Conformity, RecordStatus
from service.calibration.registry import get_method
from service.errors import InputError
from service.jobs.requests import KIND_OF_PROCEDURE, Finite, RequestBody, Text, method_per_procedure
from service.storage.feed import EVENT_TYPES
from service.storage.store.webhooks import CREDENTIALS_REFUSED

NEXT_CURSOR = "the `cursor` of the next page; null on the last page"
# http(s), a host, no user:password@ before it, no whitespace or control character anywhere
WEBHOOK_URL_PATTERN = (
    r"^https?://[^/?#@\[\]\s\x00-\x1f\x7f-\x9f\u202a-\u202e\u2066-\u2069]+"
    r"(?:[/?#][^\s\x00-\x1f\x7f-\x9f\u202a-\u202e\u2066-\u2069]*)?$"
)

# ---------------------------------------------------------------- reference standards


class CalibratedByIn(RequestBody):
    name: Annotated[
        Text,
        Field(
            min_length=1,
            max_length=200,
            examples=["Angle Calibration Laboratory AG"],
            description="the laboratory that calibrated the standard (its certificate's issuer)",
        ),
    ]
    accreditation: (
        Annotated[
            Text,
            Field(
                min_length=1,
                max_length=100,
                examples=["D-K-12345-01-00"],
                description="its accreditation number, where it has one",
            ),
        ]
        | None
    ) = None
    city: Annotated[Text, Field(min_length=1, max_length=200)] | None = None
    country_code: str = Field(
        pattern=r"^[A-Z]{2}$", description="ISO 3166-1 alpha-2", examples=["DE"]
    )


class CalibratedBy(Answer):
    name: str
    accreditation: str | None = None
    city: str | None = None
    country_code: str


class StandardIn(RequestBody):
    # a coverage factor belongs to an expanded uncertainty: given alone it is refused
    model_config = ConfigDict(
        json_schema_extra={"dependentRequired": {"coverage_factor": ["expanded_uncertainty_deg"]}}
    )

    name: Annotated[Text, Field(min_length=1, max_length=100, examples=["reference inclinometer"])]
    serial: Annotated[Text, Field(min_length=1, max_length=100)]
    model: Annotated[Text, Field(max_length=100)] | None = None
    certificate_number: Annotated[Text, Field(min_length=1, max_length=100)]
    certificate_sha256: str = Field(
        pattern=r"^[0-9a-f]{64}$",
        description="SHA-256 of the standard's calibration"
        " certificate file (64 lower-case hex digits)",
    )
    calibrated_on: dt.date
    due_on: dt.date = Field(description="after calibrated_on")
    expanded_uncertainty_deg: (
        Annotated[
            Finite,
            Field(
                gt=0,
                examples=[0.001],
                description="expanded uncertainty U of the standard's angle, in degrees, as its "
                "certificate states it; u = U / coverage_factor enters every result calibrated "
                "against it. Read from `uncertainty` when not given; a standard with neither "
                "cannot be named by a job (422)",
            ),
        ]
        | None
    ) = None
    coverage_factor: Annotated[Finite, Field(ge=1, description="the coverage factor k of U")] = 2.0
    uncertainty: Annotated[
        Text,
        Field(
            max_length=500,
            examples=["0.001 deg (k = 2)"],
            description="the certificate's wording of the uncertainty (a remark)",
        ),
    ] = ""
    calibrated_by: CalibratedByIn | None = Field(
        None,
        description="who calibrated the standard (its certificate's issuer). A certificate is "
        "issued only for a "
        "record whose standards name it: without it, the result's traceability cannot be stated",
    )

    @field_validator("due_on")
    @classmethod
    def _after_calibration(cls, due_on: dt.date, info: ValidationInfo) -> dt.date:
        calibrated_on = info.data.get("calibrated_on")
        if calibrated_on is not None and due_on <= calibrated_on:
            raise ValueError(f"{due_on} must be after calibrated_on {calibrated_on}")
        return due_on


class Standard(Answer):
    id: int
    name: str
    serial: str
    model: str | None
    certificate_number: str
    certificate_sha256: str
    calibrated_on: dt.date
    due_on: dt.date
    uncertainty: str | None
    expanded_uncertainty_deg: float | None = None
    coverage_factor: float | None = None
    created_utc: dt.datetime
    created_by: str
    status: Literal["valid", "due_soon", "past_due"]
    calibrated_by: CalibratedBy | None = None


class Standards(Answer):
    standards: list[Standard]
    next_cursor: int | None = Field(None, description=NEXT_CURSOR)


# ---------------------------------------------------------------- approvals


class ApproveIn(RequestBody):
    meaning: Literal["approval", "review"] = Field(
        "approval", description="what the signature means"
    )
    note: Annotated[Text, Field(max_length=10_000)] = ""


class RejectIn(RequestBody):
    reason: Annotated[Text, Field(min_length=1, max_length=10_000)]


class Signer(Answer):
    name: str
    function: str | None


class Approval(Answer):
    id: int
    record_id: int
    decision: Literal["approve", "reject"]
    meaning: str
    note: str | None
    actor: str = Field(description="the name of the token it was signed with")
    signer: Signer | None = Field(None, description="the person behind that token when they signed")
    time_utc: dt.datetime
    record_sha256: str
    prev_sha256: str
    sha256: str


class RecordState(Answer):
    id: int
    status: RecordStatus


class Decision(Answer):
    approval: Approval
    record: RecordState


class Approvals(Answer):
    record_id: int
    status: RecordStatus
    approvals: list[Approval]
    next_cursor: int | None = Field(None, description=NEXT_CURSOR)


# ---------------------------------------------------------------- orders


class CustomerIn(RequestBody):
    name: Annotated[Text, Field(min_length=1, max_length=200)]
    city: Annotated[Text, Field(min_length=1, max_length=200)]
    country_code: str = Field(pattern=r"^[A-Z]{2}$", description="ISO 3166-1 alpha-2")
    street: Annotated[Text, Field(max_length=200)] | None = None
    post_code: Annotated[Text, Field(max_length=20)] | None = None
    email: Annotated[Text, Field(max_length=200)] | None = None


class ParameterLimitIn(RequestBody):
    nominal: Finite = Field(
        0.0, description="the parameter's nominal value, in its unit (MODEL.json)"
    )
    max_permissible_error: Annotated[
        Finite,
        Field(
            gt=0, description="largest permissible deviation from nominal, in the parameter's unit"
        ),
    ]


class SpecificationIn(RequestBody):
    max_permissible_error_deg: Annotated[
        Finite,
        Field(
            gt=0,
            le=90,
            examples=[0.05],
            description="the largest permissible error of the item's indication (its reading minus "
            "the reference, as "
            "found, at every calibration and validation point, per axis), in degrees",
        ),
    ]
    decision_rule: Literal["simple_acceptance", "guarded_acceptance", "non_binary"] = Field(
        description="ILAC-G8: simple_acceptance passes |e| <= MPE; guarded_acceptance passes |e| "
        "<= MPE - w with w = "
        "guard_band_fraction·U; non_binary states pass, conditionalPass, conditionalFail or fail"
    )
    guard_band_fraction: (
        Annotated[
            Finite,
            Field(
                gt=0,
                le=3,
                description="guarded_acceptance only: w as a fraction of U (default 1: w = U)",
            ),
        ]
        | None
    ) = None
    parameters: (
        Annotated[
            dict[str, ParameterLimitIn],
            Field(
                max_length=50,
                description="named parameters of the model with their nominal value and largest "
                "permissible "
                "deviation (statements about them use their U as the certificate states it)",
            ),
        ]
        | None
    ) = None


class Specification(Answer):
    max_permissible_error_deg: float
    decision_rule: str
    guard_band_fraction: float | None = None
    parameters: dict[str, dict[str, float]] | None = None


class OrderIn(RequestBody):
    model_config = ConfigDict(json_schema_extra=method_per_procedure)

    lims_order_id: Annotated[Text, Field(min_length=1, max_length=100)]
    item_serial: Annotated[Text, Field(min_length=1, max_length=100)]
    item_manufacturer: (
        Annotated[
            Text,
            Field(max_length=100, description="the item's manufacturer (its certificate names it)"),
        ]
        | None
    ) = None
    item_model: (
        Annotated[
            Text, Field(max_length=100, description="the item's model (its certificate names it)")
        ]
        | None
    ) = None
    customer: CustomerIn
    procedure: Literal["stage-grid", "scale", "rotation", "turntable"]
    method: Annotated[
        Text,
        Field(
            max_length=80,
            description="a method of the procedure's kind (as for POST /calibrations)",
        ),
    ]
    due_on: dt.date | None = None
    specification: SpecificationIn | None = Field(
        None,
        description="what the item must meet: its certificate then states conformity (stage-grid "
        "orders)",
    )

    @field_validator("method")
    @classmethod
    def _known_method(cls, method: str, info: ValidationInfo) -> str:
        procedure = info.data.get("procedure")
        if procedure is not None:  # an unknown procedure is refused on its own
            try:
                get_method(KIND_OF_PROCEDURE[procedure], method)
            except InputError as exc:
                raise ValueError(str(exc)) from None
        return method


class JobLink(Answer):
    id: int
    state: JobState


class RecordLink(Answer):
    id: int
    version: int
    status: RecordStatus


class CertificateLink(Answer):
    id: int
    number: str
    record_id: int
    sha256: str


class Order(Answer):
    id: int
    lims_order_id: str
    item_serial: str
    item_manufacturer: str | None = None
    item_model: str | None = None
    customer: dict[str, object]
    procedure: str
    method: str
    due_on: dt.date | None
    created_utc: dt.datetime
    created_by: str
    jobs: list[JobLink]
    records: list[RecordLink]
    certificates: list[CertificateLink]
    state: str = Field(
        description="open, in_progress, measured, approved, rejected, certified or failed"
    )
    specification: Specification | None = None
    conformity: Conformity | None = Field(
        None,
        description="the newest record's statements of conformity, once it "
        "is measured (with a specification)",
    )


# ---------------------------------------------------------------- the feed


class Event(Answer):
    id: str = Field(description="evt_<n>, increasing")
    type: str = Field(description=f"one of {', '.join(EVENT_TYPES)}")
    time_utc: str
    data: dict[str, object]


class Feed(Answer):
    events: list[Event]
    next_cursor: str = Field(description="hand back as `cursor` on the next poll")


# ---------------------------------------------------------------- webhooks


EventType = Literal[*EVENT_TYPES, "*"]  # type: ignore[valid-type]


class WebhookIn(RequestBody):
    url: Annotated[
        Text,
        Field(
            max_length=2000,
            examples=["https://lims.example.org/tiltlab-hook"],
            json_schema_extra={"pattern": WEBHOOK_URL_PATTERN},
            description="an http:// or https:// URL with a host and without credentials",
        ),
    ]
    events: Annotated[
        list[EventType],
        Field(
            min_length=1,
            max_length=50,
            description=f"event types ({', '.join(EVENT_TYPES)}), or ['*'] for all",
        ),
    ]

    @field_validator("url")
    @classmethod
    def _web_url(cls, url: str) -> str:
        try:
            parts = urlsplit(url)
            host = parts.hostname
        except ValueError as exc:
            raise ValueError(f"not a URL: {exc}") from None
        if parts.scheme not in ("http", "https") or not host:
            raise ValueError("a webhook URL must be http:// or https:// with a host")
        if parts.username is not None or parts.password is not None:
            raise ValueError(CREDENTIALS_REFUSED)
        return url

    @field_validator("events")
    @classmethod
    def _known_events(cls, events: list[str]) -> list[str]:
        unknown = [event for event in events if event != "*" and event not in EVENT_TYPES]
        if unknown:
            raise ValueError(
                f"{', '.join(unknown)[:200]} unknown; event types are {', '.join(EVENT_TYPES)} (or "
                "'*')"
            )
        return events


class Webhook(Answer):
    id: int
    url: str
    events: list[str]
    created_utc: dt.datetime
    created_by: str | None = None


class NewWebhook(Webhook):
    secret: str = Field(description="the signing secret, shown this once")


class Webhooks(Answer):
    webhooks: list[Webhook]
    next_cursor: int | None = Field(None, description=NEXT_CURSOR)


class Attempt(Answer):
    time_utc: dt.datetime
    status_code: int | None
    error: str | None
    duration_s: float | None


class Delivery(Answer):
    id: int
    event_id: str
    event_type: str
    state: str = Field(description="pending, delivered or failed")
    attempts: int
    next_attempt_utc: dt.datetime | None
    delivered_utc: dt.datetime | None
    last_status_code: int | None
    last_error: str | None
    log: list[Attempt]


class Deliveries(Answer):
    webhook_id: int
    deliveries: list[Delivery]
    next_cursor: int | None = Field(None, description=NEXT_CURSOR)
