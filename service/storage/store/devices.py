"""Benches and devices: registration, changes (audited with before/after) and lookups."""

from __future__ import annotations

from collections.abc import Collection, Mapping
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session

from service.errors import InputError
from service.storage.errors import ConflictError
from service.storage.models import Bench, Device
from service.storage.store.checks import optional_text, require_doc, require_text
from service.storage.store.database import Database
from service.storage.store.lookups import device_in, row_in


class DevicesRepo:
    def __init__(self, db: Database) -> None:
        self._db = db

    def add_bench(
        self,
        name: str,
        *,
        actor: str,
        stage_model: str | None = None,
        stage_serial: str | None = None,
        port: str | None = None,
        port_settings: Mapping[str, object] | None = None,
    ) -> Bench:
        with self._db.transaction() as session:
            name = require_text("bench name", name)
            if session.scalar(sa.select(Bench.id).where(Bench.name == name)) is not None:
                raise ConflictError(f"a bench named {name!r} already exists")
            return self._insert_bench(
                session,
                name,
                actor=actor,
                stage_model=stage_model,
                stage_serial=stage_serial,
                port=port,
                port_settings=port_settings,
            )

    def _insert_bench(
        self,
        session: Session,
        name: str,
        *,
        actor: str,
        stage_model: str | None = None,
        stage_serial: str | None = None,
        port: str | None = None,
        port_settings: Mapping[str, object] | None = None,
    ) -> Bench:
        port = optional_text("port", port, 200)
        bench = Bench(
            name=name,
            stage_model=optional_text("stage_model", stage_model, 100),
            stage_serial=optional_text("stage_serial", stage_serial, 100),
            port=port,
            port_settings=require_doc("port_settings", port_settings or {}),
        )
        session.add(bench)
        session.flush()
        self._db.audit(
            session, actor, "bench.create", "bench", bench.id, {"name": name, "port": port}
        )
        return bench

    def add_device(
        self,
        model: str,
        serial: str,
        role: str,
        *,
        actor: str,
        bench_id: int | None = None,
        port: str | None = None,
        port_settings: Mapping[str, object] | None = None,
    ) -> Device:
        with self._db.transaction() as session:
            model, serial, role = (
                require_text("model", model),
                require_text("serial", serial),
                require_text("role", role, 40),
            )
            port = optional_text("port", port, 200)
            if bench_id is not None:
                row_in(session, Bench, bench_id, "bench")
            existing = session.scalar(
                sa.select(Device.id).where(Device.model == model, Device.serial == serial)
            )
            if existing is not None:
                raise ConflictError(f"device {model} s/n {serial} already exists (id {existing})")
            return self._insert_device(
                session,
                model,
                serial,
                role,
                actor=actor,
                bench_id=bench_id,
                port=port,
                port_settings=port_settings,
            )

    def _insert_device(
        self,
        session: Session,
        model: str,
        serial: str,
        role: str,
        *,
        actor: str,
        bench_id: int | None,
        port: str | None,
        port_settings: Mapping[str, object] | None,
    ) -> Device:
        role = require_text("role", role, 40)
        port = optional_text("port", port, 200)
        if bench_id is not None:
            row_in(session, Bench, bench_id, "bench")
        device = Device(
            model=model,
            serial=serial,
            role=role,
            bench_id=bench_id,
            port=port,
            port_settings=require_doc("port_settings", port_settings or {}),
        )
        session.add(device)
        session.flush()
        self._db.audit(
            session,
            actor,
            "device.create",
            "device",
            device.id,
            {"model": model, "serial": serial, "role": role, "bench_id": bench_id, "port": port},
        )
        return device

    def update_device(self, device_id: int, *, actor: str, **changes: Any) -> Device:
        allowed = {"role", "bench_id", "port", "port_settings"}
        unknown = set(changes) - allowed
        if unknown:
            raise InputError(
                f"cannot change {sorted(unknown)} of a device; changeable: {sorted(allowed)}"
            )
        with self._db.transaction() as session:
            return self._change_device(
                session, device_in(session, device_id), actor=actor, changes=changes
            )

    def _change_device(
        self, session: Session, device: Device, *, actor: str, changes: dict[str, object]
    ) -> Device:
        if changes.get("bench_id") is not None:
            row_in(session, Bench, changes["bench_id"], "bench")
        if "role" in changes:
            changes["role"] = require_text("role", changes["role"], 40)
        if "port" in changes:
            changes["port"] = optional_text("port", changes["port"], 200)
        if "port_settings" in changes:
            changes["port_settings"] = require_doc("port_settings", changes["port_settings"] or {})
        before = {k: getattr(device, k) for k in changes}
        for key, value in changes.items():
            setattr(device, key, value)
        self._db.audit(
            session,
            actor,
            "device.update",
            "device",
            device.id,
            {"before": before, "after": changes},
        )
        return device

    def ensure_bench(self, name: str, *, actor: str, port: str | None = None) -> Bench:
        """The bench of that name, registered now if this database does not know it yet.

        One serialised transaction looks and registers: daemons starting together with the same
        bench name make one bench, and every one of them gets it."""
        name = require_text("bench name", name)
        # the usual case, a bench registered before, needs no write
        with self._db.session() as session:
            bench = session.scalar(sa.select(Bench).where(Bench.name == name))
        if bench is not None:
            return bench
        with self._db.transaction() as session:
            bench = session.scalar(sa.select(Bench).where(Bench.name == name))
            return (
                bench
                if bench is not None
                else self._insert_bench(session, name, actor=actor, port=port)
            )

    def ensure_device(
        self, model: str, serial: str, role: str, *, actor: str, bench_id: int, port: str | None
    ) -> Device:
        """The device of that model and serial number, registered now or moved to this bench, role
        and port.

        One serialised transaction looks, registers or changes it: daemons that find the same
        instrument while starting together make one device (an instrument is where it was seen
        last)."""
        model, serial = require_text("model", model), require_text("serial", serial)
        wanted = {"bench_id": bench_id, "port": port, "role": role}
        with self._db.session() as session:
            device = session.scalar(
                sa.select(Device).where(Device.model == model, Device.serial == serial)
            )
        if device is not None and all(
            getattr(device, key) == value for key, value in wanted.items()
        ):
            return device
        with self._db.transaction() as session:
            device = session.scalar(
                sa.select(Device).where(Device.model == model, Device.serial == serial)
            )
            if device is None:
                return self._insert_device(
                    session,
                    model,
                    serial,
                    role,
                    actor=actor,
                    bench_id=bench_id,
                    port=port,
                    port_settings=None,
                )
            changes: dict[str, object] = {
                key: value for key, value in wanted.items() if getattr(device, key) != value
            }
            return (
                self._change_device(session, device, actor=actor, changes=changes)
                if changes
                else device
            )

    def get_device(self, device_id: int) -> Device:
        with self._db.session() as session:
            return device_in(session, device_id)

    def find_device(self, model: str, serial: str) -> Device | None:
        with self._db.session() as session:
            return session.scalar(
                sa.select(Device).where(Device.model == model, Device.serial == serial)
            )

    def all(self) -> list[Device]:
        with self._db.session() as session:
            return list(session.scalars(sa.select(Device).order_by(Device.id)))

    def bench_names_of_devices(self, device_ids: Collection[int]) -> dict[int, str]:
        """device id -> the name of the bench it was last registered on, for devices of any daemon
        of the lab."""
        if not device_ids:
            return {}
        with self._db.session() as session:
            rows = session.execute(
                sa.select(Device.id, Bench.name)
                .join(Bench, Device.bench_id == Bench.id)
                .where(Device.id.in_(list(device_ids)))
            )
            return {int(device_id): str(name) for device_id, name in rows}

    def bench_id_of(self, name: str) -> int | None:
        """The id of the bench of that name, whichever daemon of the lab runs it."""
        with self._db.session() as session:
            bench_id: int | None = session.scalar(sa.select(Bench.id).where(Bench.name == name))
            return bench_id

    def device_ids_of_bench(self, name: str) -> list[int] | None:
        """The devices registered on the bench of that name (whichever daemon runs it); None if no
        bench has it."""
        with self._db.session() as session:
            bench_id = session.scalar(sa.select(Bench.id).where(Bench.name == name))
            if bench_id is None:
                return None
            return list(session.scalars(sa.select(Device.id).where(Device.bench_id == bench_id)))

    def benches(self) -> list[Bench]:
        with self._db.session() as session:
            return list(session.scalars(sa.select(Bench).order_by(Bench.id)))
