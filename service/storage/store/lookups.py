"""Lookups inside a transaction, shared by the repositories that check another aggregate's row."""

from __future__ import annotations

from sqlalchemy.orm import Session

from service.storage.errors import UnknownEntity
from service.storage.models import CalibrationJob, Device


def device_in(s: Session, device_id: int) -> Device:
    device = s.get(Device, device_id) if isinstance(device_id, int) else None
    if device is None:
        raise UnknownEntity(f"device {device_id!r} does not exist")
    return device


def job_in(s: Session, job_id: int) -> CalibrationJob:
    job = s.get(CalibrationJob, job_id) if isinstance(job_id, int) else None
    if job is None:
        raise UnknownEntity(f"job {job_id!r} does not exist")
    return job
