"""Admission of a calibration request, before anything moves: the procedure's checks against the
bench, the traceability of the named reference standards and order, and what a repeated
Idempotency-Key answers.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
from typing import Any

from service.bench.readings import OUTLIER_RULE
from service.bench.runtime import BenchBusy, BenchRuntime
from service.calibration.budget import ReferenceStandard
from service.jobs import registry
from service.jobs.job_parameters import AdaptiveAdmission, JobParameters, RequestJSON
from service.jobs.procedure import Plan
from service.jobs.requests import CalibrationRequest, RequestProblem
from service.jobs.stage_grid import APPROACH_DEG
from service.storage.canonical import sha256_hex
from service.storage.errors import UnknownEntity
from service.storage.models import CalibrationJob
from service.storage.store import JobsRepo, OrdersRepo, StandardsRepo
from service.storage.store.jobs import IdempotencyMismatch
from service.storage.store.standards import StandardNotUsable

IDEMPOTENCY_ROUTE = "calibrations"


class RegisteredStandard(ReferenceStandard):
    """A registered reference standard a job named, as its record keeps it (the traceability of
    the result)."""

    id: int
    certificate_sha256: str


class Admission:
    def __init__(
        self,
        jobs: JobsRepo,
        orders: OrdersRepo,
        standards: StandardsRepo,
        *,
        require_conditions: bool = False,
    ) -> None:
        self.jobs, self.orders, self.registered_standards = jobs, orders, standards
        self.require_conditions = require_conditions

    def plan(self, req: CalibrationRequest, bench: BenchRuntime) -> Plan[Any]:
        """Blocking (database): the points a request will measure; RequestProblem names the field
        that cannot be used."""
        self.check_traceability(req)
        self.check_conditions(req, bench)
        procedure = registry.procedure_named(req.procedure)
        if procedure is None:
            raise RequestProblem(
                "procedure",
                f"{req.procedure!r} jobs are not run by this daemon version; "
                f"it runs {registry.names()} jobs",
            )
        plan = procedure.plan(req, bench)
        if req.design == "adaptive":
            plan = dataclasses.replace(
                plan, extra={"adaptive": self.adaptive_admission(req, bench)}
            )
        return plan

    def adaptive_admission(self, req: CalibrationRequest, bench: BenchRuntime) -> AdaptiveAdmission:
        """Blocking (database): an adaptive job's target against what every corrected tilt carries
        whatever is measured (the named standards' u = U/k, the sensors' resolutions r/sqrt(12)); a
        target at or below that floor is refused naming it."""
        from service.calibration.adaptive_design import K_EXPANDED
        from service.jobs.budgets import ROLE_WORDS, resolutions_deg

        u2 = 0.0
        for standard in self.standards(req.reference_standards):
            expanded, k = standard["expanded_uncertainty_deg"], standard["coverage_factor"]
            if expanded is not None and k:
                u2 += (float(expanded) / float(k)) ** 2
        u2 += sum(
            (resolution / math.sqrt(12.0)) ** 2
            for role, resolution in resolutions_deg(bench).items()
            if role in ROLE_WORDS and resolution
        )
        floor = K_EXPANDED * math.sqrt(u2)
        target = req.target_expanded_uncertainty_deg
        assert target is not None  # the request's validator requires it with design adaptive
        if target <= floor:
            raise RequestProblem(
                "target_expanded_uncertainty_deg",
                f"{target:g} deg cannot be reached on bench {bench.name!r}: the reference "
                "standards' and the sensors' resolutions' part of every corrected tilt is "
                f"already {floor:.3g} deg (expanded, k = 2); ask for more than that",
            )
        return {"fixed_u_deg": math.sqrt(u2), "floor_fixed_deg": floor}

    def check_traceability(self, req: CalibrationRequest) -> None:
        """Every reference standard the job names is registered and not past its due date; the order
        exists."""
        try:
            self.registered_standards.usable_standards(
                req.reference_standards, on=dt.datetime.now(dt.UTC).date()
            )
        except StandardNotUsable as exc:
            raise RequestProblem(exc.field, exc.reason) from None
        if req.order_id is not None:
            try:
                self.orders.get(req.order_id)
            except UnknownEntity:
                raise RequestProblem(
                    "order_id", f"there is no order {req.order_id} (POST /orders)"
                ) from None

    def check_conditions(self, req: CalibrationRequest, bench: BenchRuntime) -> None:
        """Where the laboratory requires conditions: a bench with an ambient sensor records them,
        any other job must state the ambient temperature."""
        if not self.require_conditions or bench.devices.ambient_sensor() is not None:
            return
        if req.conditions is None or req.conditions.ambient_temperature_c is None:
            raise RequestProblem(
                "conditions.ambient_temperature_c",
                f"this laboratory requires the ambient conditions of every calibration, and bench "
                f"{bench.name!r} has no ambient sensor: give conditions.ambient_temperature_c "
                '{"value": <°C>, "standard_uncertainty": <°C>} as read on a calibrated thermometer',
            )

    def standards(self, ids: list[int]) -> list[RegisteredStandard]:
        """Blocking (database): the registered standards a job named, as its record keeps them (the
        traceability of the result)."""
        return [
            {
                "id": st.id,
                "name": st.name,
                "serial": st.serial,
                "certificate_id": st.certificate_number,
                "certificate_sha256": st.certificate_sha256,
                "expanded_uncertainty_deg": st.expanded_uncertainty_deg,
                "coverage_factor": st.coverage_factor,
            }
            for st in map(self.registered_standards.get, ids)
        ]

    @staticmethod
    def parameters(body: RequestJSON, bench: BenchRuntime, plan: Plan[Any]) -> JobParameters:
        """What a job keeps of its request: the request, its points and how they are measured."""
        return {
            **plan.extra,
            "request": body,
            "fit_points": plan.fit_points,
            "validation_points": plan.validation_points,
            "outlier_rule": OUTLIER_RULE,
            "approach": f"from below on both axes by {APPROACH_DEG} deg",
            "device_ids": {
                read_role: bench.device_ids.get(read_role) for read_role in plan.read_roles
            },
        }

    def replay(self, bench: BenchRuntime, key: str, body: RequestJSON) -> CalibrationJob:
        """Blocking (database): the job an earlier request with this Idempotency-Key made. A busy
        bench still answers a repeated request with its job; a key the database does not know is
        409."""
        seen = self.jobs.idempotency_key(key, route=IDEMPOTENCY_ROUTE)
        if seen is None:
            raise BenchBusy(f"bench {bench.name!r} is held by {bench.holder}")
        if seen.request_sha256 != sha256_hex(body):
            raise IdempotencyMismatch(
                f"Idempotency-Key {key!r} was used for another request body (job {seen.job_id});"
                " use a new key for a new request"
            )
        if seen.job_id is None:
            raise IdempotencyMismatch(
                f"Idempotency-Key {key!r} belongs to a request that made no job"
            )
        return self.jobs.get_job(seen.job_id)
