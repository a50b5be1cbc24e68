"""Service configuration: environment variables `TILTLAB_*`, an optional TOML file, defaults.

At the package root because the API, storage, the fleet, the commands and migrations/env.py all read
it.

Precedence, highest first: explicit keyword arguments, environment variables, the TOML file
named by `TILTLAB_CONFIG`, the defaults below. The defaults suit a single bench on one PC.
"""

from __future__ import annotations

import os
import socket
import tomllib
from collections.abc import Mapping
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

import platformdirs
from pydantic import Field, ValidationError, model_validator
from pydantic_settings import (
    BaseSettings,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

from service.errors import InputError

CONFIG_ENV = "TILTLAB_CONFIG"


def default_data_dir() -> Path:
    return Path(platformdirs.user_data_dir("tiltlab"))


_STAGE_ONLY: tuple[Literal["stage", "rotary"], ...] = ("stage",)


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="TILTLAB_", extra="ignore")

    data_dir: Path = Field(default_factory=default_data_dir)
    # Empty means the SQLite file `tiltlab.db` in data_dir.
    database_url: str = ""
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    # The simulated bench the service drives: a stage scenario preset name or a scenario file.
    bench_scenario: str = "seed000"
    # Without a bench configuration: the simulated benches to run ("stage", "rotary" or both).
    sim_benches: list[Literal["stage", "rotary"]] = Field(
        default_factory=lambda: list(_STAGE_ONLY), min_length=1
    )
    # The scenario of the simulated rotary bench (rotation and turntable physics).
    rotary_scenario: str = "seed002-sim"
    # How the simulated instruments are reached: "pty" (pseudo-terminals, as USB adapters) or
    # "loopback" (in-memory lines of this process: the same drivers and codecs without the pty, for
    # in-process tests).
    sim_transport: Literal["pty", "loopback"] = "pty"
    # The simulated bench runs this many times faster than real time (motion, settling, output
    # intervals).
    sim_speed: float = Field(1.0, gt=0, le=1000)
    # A bench configuration (TOML) naming real ports; empty means the simulated stage bench.
    bench_config: Path | None = None
    # "token": bearer tokens with scopes; "none": no authentication, refused unless bound to
    # loopback.
    auth: Literal["token", "none"] = "token"
    # Where the first start writes the lab's first admin token (mode 0600); empty means admin.token
    # in data_dir. Daemons of a fleet that share a folder name the same file, so whichever of them
    # starts first on a new database, the token is found in the one place.
    admin_token_file: Path | None = None
    # Live streams (WebSocket): messages waiting per client; a client whose queue has stayed full
    # (every message dropped) for stream_slow_close_s real seconds is closed (1013).
    stream_queue_size: int = Field(100, ge=2, le=100_000)
    stream_slow_close_s: float = Field(10.0, gt=0, allow_inf_nan=False)
    # A request body larger than this is refused (413) before it is read, with or without a token.
    max_body_bytes: int = Field(1_048_576, ge=1024)
    # The most points a calibration job's grid may have (more is refused with 422): a huge grid
    # would take days and make rows the job list must read.
    max_grid_points: int = Field(10_000, ge=1, le=1_000_000)
    # A request's head (request line and headers) larger than this, or with more header lines than
    # max_headers, is refused (431) before it is parsed; one not complete within header_timeout_s of
    # its first byte (or of the connection, for a client that sends nothing) is answered 408 and
    # closed.
    max_header_bytes: int = Field(32_768, ge=4096, le=1_048_576)
    max_headers: int = Field(100, ge=10, le=10_000)
    header_timeout_s: float = Field(10.0, gt=0, le=600, allow_inf_nan=False)
    # Open connections (HTTP and WebSocket) one client address may hold; one more is answered 429
    # and closed.
    max_connections_per_client: int = Field(64, ge=1, le=100_000)
    # A request's database work (the token check included) that has not finished after this long is
    # answered 503 naming the database; it runs in a pool of db_request_threads threads of its own,
    # and when every one of them is waiting on the database a request is answered 503 at once.
    db_request_timeout_s: float = Field(10.0, gt=0, le=600, allow_inf_nan=False)
    db_request_threads: int = Field(8, ge=1, le=256)
    # Unknown tokens from one client address: failed_tokens_burst may fail in a row, then one more
    # every failed_tokens_every_s seconds; beyond that 429 with Retry-After (a token the daemon
    # knows always passes).
    failed_tokens_burst: int = Field(20, ge=1, le=100_000)
    failed_tokens_every_s: float = Field(2.0, gt=0, le=3600, allow_inf_nan=False)
    # Reading-stream snapshots with history are built at most max_snapshots at a time, with at most
    # snapshot_queue waiting; a connection beyond that is closed 1013 (try again later).
    max_snapshots: int = Field(2, ge=1, le=64)
    snapshot_queue: int = Field(8, ge=0, le=1000)
    # Diagnoses queued or running at once; one more is answered 503 with Retry-After.
    max_diagnoses: int = Field(4, ge=1, le=1000)
    # The free space the data directory must keep: below it /ready is 503, a job does not start
    # (507) and a running job stops (resumable) before the disk fills.
    min_free_mb: float = Field(100.0, ge=0, allow_inf_nan=False)

    # Free-running monitoring samples older than this are thinned or dropped; calibration data never
    # are.
    monitoring_retention_days: float = Field(30.0, gt=0)
    monitoring_retention_policy: Literal["thin", "drop"] = "thin"
    # "thin" keeps the first sample per device in each interval of this length.
    monitoring_thin_interval_s: float = Field(60.0, gt=0)

    # SampleWriter: at most queue + one batch of handed-over samples can be lost on a hard kill.
    sample_queue_capacity: int = Field(50_000, ge=1)
    sample_batch_size: int = Field(5_000, ge=1)
    sample_put_timeout_s: float = Field(5.0, gt=0)

    # A writer waits this long for the SQLite write lock; a loaded disk can hold a checkpoint for
    # seconds.
    sqlite_busy_timeout_ms: int = Field(30_000, ge=0)
    # At start-up an unreachable database is retried with back-off for this long before giving up.
    database_wait_s: float = Field(30.0, ge=0, allow_inf_nan=False)
    # While the daemon runs, a database that goes away is waited for: a job's writes wait (the job
    # pauses) and the job fails (database_unreachable) only once the outage has lasted this long.
    db_outage_s: float = Field(300.0, gt=0, allow_inf_nan=False)

    # The laboratory as its certificates name it (a certificate is refused until name, city and
    # country are set).
    lab_name: str = ""
    lab_city: str = ""
    lab_country_code: str = Field("", pattern=r"^([A-Z]{2})?$")
    lab_street: str = ""
    lab_post_code: str = ""
    lab_email: str = ""
    # Accreditation number printed as the calibration laboratory code, if any.
    lab_accreditation: str = ""
    # The lab's key and X.509 certificate (PEM files) that sign every certificate it issues (an
    # enveloped XML signature: the file itself is tamper-evident); both or neither.
    certificate_signing_key: str = ""
    certificate_signing_cert: str = ""
    # Certificate numbers are PREFIX-YEAR-RECORD (e.g. TL-2026-000042).
    certificate_prefix: str = Field("TL", pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,19}$")
    # A standard.due_soon event is sent this many days before a reference standard is due.
    standards_due_soon_days: int = Field(30, ge=0)
    # Webhook deliveries: first retry after this long, doubling each time, at most this many
    # attempts.
    webhook_retry_base_s: float = Field(5.0, gt=0, allow_inf_nan=False)
    webhook_retry_max_s: float = Field(3600.0, gt=0, allow_inf_nan=False)
    webhook_max_attempts: int = Field(12, ge=1)
    webhook_timeout_s: float = Field(10.0, gt=0, allow_inf_nan=False)

    # The fleet: this daemon's name among the lab's daemons, and the NATS server (JetStream) they
    # share. Without a broker URL the daemon runs alone.
    node: str = Field(
        default_factory=socket.gethostname,
        min_length=1,
        max_length=64,
        pattern=r"^[A-Za-z0-9][A-Za-z0-9_-]*$",
    )
    broker_url: str | None = Field(None, pattern=r"^(nats|tls)://")
    # A node renews its benches' leases this often (lease_s / 3); a node silent for lease_s is
    # offline.
    fleet_lease_s: float = Field(6.0, ge=1, le=600, allow_inf_nan=False)
    # Readings published to the fleet per bench and second (decimated from the sensors' rate).
    fleet_rate_hz: float = Field(10.0, gt=0, le=100, allow_inf_nan=False)
    # A bench command carried to another node waits this long for its answer (levelling can take a
    # while).
    fleet_command_timeout_s: float = Field(120.0, gt=0, allow_inf_nan=False)
    # The simulated stage bench's name (bench names are unique in a fleet); empty keeps the
    # scenario's.
    sim_bench_name: str = Field("", max_length=64, pattern=r"^([A-Za-z0-9][A-Za-z0-9_-]*)?$")
    # Simulated benches get an ambient sensor (a thermo-hygrometer reading the laboratory's air).
    sim_ambient_sensor: bool = False
    # A calibration job must state the laboratory's ambient temperature: from the bench's ambient
    # sensor, or entered with the request (`conditions.ambient_temperature_c`); a job without it is
    # refused (422).
    require_conditions: bool = False

    def __init__(self, **values: Any) -> None:
        """As BaseSettings, but an unusable value or file is an InputError of one line naming it."""
        try:
            super().__init__(**values)
        except ValidationError as exc:
            raise InputError(_describe(exc)) from None
        except tomllib.TOMLDecodeError as exc:
            raise InputError(
                f"{CONFIG_ENV}={os.environ.get(CONFIG_ENV, '')}: not valid TOML: {exc}"
            ) from None

    @model_validator(mode="after")
    def _fill_database_url(self) -> Settings:
        self.data_dir = Path(self.data_dir).expanduser()
        if self.admin_token_file is not None:
            self.admin_token_file = (
                Path(self.admin_token_file).expanduser()
                if str(self.admin_token_file) not in ("", ".")
                else None
            )
        if not self.database_url:
            self.database_url = f"sqlite:///{(self.data_dir / 'tiltlab.db').as_posix()}"
        if self.sample_batch_size > self.sample_queue_capacity:
            raise ValueError("sample_batch_size must not exceed sample_queue_capacity")
        return self

    @property
    def admin_token_path(self) -> Path:
        """The file of the lab's first admin token: TILTLAB_ADMIN_TOKEN_FILE, else admin.token in
        the data directory."""
        return self.admin_token_file or self.data_dir / "admin.token"

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        sources: list[PydanticBaseSettingsSource] = [init_settings, env_settings]
        config_file = os.environ.get(CONFIG_ENV, "")
        if config_file:
            path = Path(config_file).expanduser()
            if not path.is_file():
                raise InputError(f"{CONFIG_ENV}={config_file}: no such configuration file")
            toml = TomlConfigSettingsSource(settings_cls, toml_file=path)
            _refuse_unknown_keys(config_file, toml.toml_data, set(settings_cls.model_fields))
            sources.append(toml)
        return tuple(sources)


def _refuse_unknown_keys(config_file: str, data: Mapping[str, object], known: set[str]) -> None:
    """A key the settings do not have (a typo such as `sim_sped`) is refused, not silently
    ignored."""
    import difflib

    for key in data:
        if key not in known:
            near = difflib.get_close_matches(key.lower(), sorted(known), n=1)
            hint = f" (did you mean {near[0]}?)" if near else ""
            raise InputError(
                f"{CONFIG_ENV}={config_file}: {key}: no such setting{hint}; "
                "the settings are listed in docs/storage.md"
            )


def _describe(exc: ValidationError) -> str:
    parts = []
    for err in exc.errors():
        msg = err["msg"].removeprefix("Value error, ")
        if err["loc"]:
            name = str(err["loc"][0])
            parts.append(f"{name} (TILTLAB_{name.upper()}): {msg}; got {err['input']!r}")
        else:
            parts.append(msg)
    return "configuration: " + "; ".join(parts)


def ensure_data_dir(settings: Settings) -> Path:
    """The data directory, created if missing and proved writable, or a one-line InputError naming
    it."""
    import tempfile

    path = Path(settings.data_dir)
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as exc:
        raise InputError(
            f"TILTLAB_DATA_DIR={path}: cannot create or write this folder ({exc.strerror}); "
            "set TILTLAB_DATA_DIR to a folder this user can write"
        ) from None
    return path


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings (cached; call `get_settings.cache_clear()` after changing the
    environment)."""
    return Settings()
