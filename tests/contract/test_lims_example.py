"""The complete LIMS example that docs/lims.md quotes (`docs/examples/lims/`) is what
`docs/examples/lims/flow.py` writes today: run again, the requests, their statuses, the record's
fields, the budget's rows and the certificate's element tree are the same (the measured values,
times and the signature differ from run to run), and the committed certificate validates against the
DCC schema."""

from __future__ import annotations

import json
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

from tests.helpers.external_checks import xmllint_errors

EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "examples" / "lims"


def _keys(value: object, path: str = "") -> set[str]:
    """Every key path of a JSON document (list items merged)."""
    if isinstance(value, dict):
        out = {f"{path}/{key}" for key in value}
        for key, item in value.items():
            out |= _keys(item, f"{path}/{key}")
        return out
    if isinstance(value, list):
        return set().union(*(_keys(item, f"{path}[]") for item in value)) if value else set()
    return set()


def _tags(xml: bytes) -> set[str]:
    root = ET.fromstring(xml)
    out: set[str] = set()

    def walk(element: ET.Element, path: str) -> None:
        here = f"{path}/{element.tag}"
        out.add(here)
        for child in element:
            walk(child, here)

    walk(root, "")
    return out


def _budget_rows(text: str) -> list[str]:
    """The budget table's result and component names (not its numbers)."""
    rows = [line.split("|")[1:3] for line in text.splitlines() if line.startswith("|")]
    return [
        f"{result.strip()} | {component.strip()}"
        for result, component in rows[2:]
        if not component.strip().startswith("**combined**")
    ]


def test_the_committed_example_is_what_the_flow_writes_today(tmp_path: Path) -> None:
    ran = subprocess.run(
        [sys.executable, str(EXAMPLE / "flow.py"), "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert ran.returncode == 0, ran.stdout + ran.stderr
    committed = json.loads((EXAMPLE / "requests.json").read_text())
    fresh = json.loads((tmp_path / "requests.json").read_text())
    assert [(r["request"], r["status"]) for r in committed] == [
        (r["request"], r["status"]) for r in fresh
    ]
    assert [_keys(r.get("body")) for r in committed] == [_keys(r.get("body")) for r in fresh]
    assert [_keys(r["answer"]) for r in committed] == [_keys(r["answer"]) for r in fresh]
    for name in ("record.json", "order.json", "certificate_issued.json"):
        assert _keys(json.loads((EXAMPLE / name).read_text())) == _keys(
            json.loads((tmp_path / name).read_text())
        ), name
    assert _budget_rows((EXAMPLE / "budget.md").read_text()) == _budget_rows(
        (tmp_path / "budget.md").read_text()
    )
    assert _tags((EXAMPLE / "certificate.xml").read_bytes()) == _tags(
        (tmp_path / "certificate.xml").read_bytes()
    )
    assert xmllint_errors((EXAMPLE / "certificate.xml").read_bytes()) == []
