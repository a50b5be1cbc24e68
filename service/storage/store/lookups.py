"""Lookups inside a transaction: a row by its id, or the error that names what does not exist."""

from __future__ import annotations

from typing import TypeVar

from sqlalchemy.orm import Session

from service.storage.errors import UnknownEntity
from service.storage.models import CalibrationJob, Device

T = TypeVar("T")


def row_in(session: Session, model: type[T], key: object, what: str) -> T:
    """The row of `model` whose id is `key`; UnknownEntity naming it as `what` when there is none
    (or the id is not an integer, which no row has)."""
    row = session.get(model, key) if isinstance(key, int) else None
    if row is None:
        raise UnknownEntity(f"{what} {key!r} does not exist")
    return row


def device_in(session: Session, device_id: int) -> Device:
    return row_in(session, Device, device_id, "device")


def job_in(session: Session, job_id: int) -> CalibrationJob:
    return row_in(session, CalibrationJob, job_id, "job")
