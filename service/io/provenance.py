"""Where an artefact came from: tiltlab version, UTC time, the command, and the SHA-256 of each
input file, so a model or report found on a share years later can be traced to the data it was made
from."""

from __future__ import annotations

import datetime as dt
import hashlib
from collections.abc import Mapping
from pathlib import Path
from typing import TypedDict, cast


class ProvenanceInput(TypedDict):
    """One input file of an artefact: where it was read, and the SHA-256 of its bytes (hex)."""

    path: str
    sha256: str


class Provenance(TypedDict):
    """Where an artefact came from, as MODEL.json files and reports carry it (`provenance`)."""

    tiltlab_version: str
    utc: str  # ISO 8601 to the second, with a Z
    command: str
    inputs: dict[str, ProvenanceInput]  # by the input's role (option name)


def sha256_of(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def provenance(command: str, inputs: Mapping[str, str | Path | None]) -> Provenance:
    """The provenance record; `inputs` maps each input's role (option name) to its file."""
    from service import __version__

    files: dict[str, ProvenanceInput] = {
        role: {"path": str(path), "sha256": sha256_of(path)}
        for role, path in inputs.items()
        if path is not None and Path(path).is_file()
    }
    return {
        "tiltlab_version": __version__,
        "utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds").replace("+00:00", "Z"),
        "command": command,
        "inputs": files,
    }


def provenance_lines(record: Mapping[str, object]) -> list[str]:
    """The record as short lines for a page or a report: a `Provenance` as read back (a key
    missing shows as ?)."""
    lines = [
        f"tiltlab {record.get('tiltlab_version', '?')}, {record.get('utc', '?')}",
        f"command: {record.get('command', '?')}",
    ]
    inputs = cast("Mapping[str, ProvenanceInput]", record.get("inputs") or {})
    for role, input_file in inputs.items():
        lines.append(f"{role}: {input_file['path']} (SHA-256 {input_file['sha256']})")
    return lines
