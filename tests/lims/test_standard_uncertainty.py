"""A reference standard's uncertainty is a number: given, read from the certificate's wording,
migrated, and refused where it would be used when it cannot be read."""

from __future__ import annotations

import datetime as dt

import pytest
import sqlalchemy as sa

from service.errors import InputError
from service.storage.migrate import downgrade, upgrade
from service.storage.stated_uncertainty import parse_stated_uncertainty
from service.storage.store.standards import StandardNotUsable

BASE = {
    "name": "reference inclinometer",
    "serial": "REF-77",
    "certificate_number": "C-1",
    "certificate_sha256": "ab" * 32,
    "calibrated_on": "2026-01-10",
    "due_on": "2027-01-10",
}
ON = dt.date(2026, 11, 24)


@pytest.mark.parametrize(
    ("text", "U_deg", "k"),
    [
        ("0.001 deg (k = 2)", 0.001, 2.0),
        ("U = 3.6 arcsec, k = 2", 3.6 / 3600, 2.0),
        ("±0.5″ (k=2.5)", 0.5 / 3600, 2.5),
        ("0.02 ° (k = 2)", 0.02, 2.0),
    ],
)
def test_a_certificates_wording_reads_as_degrees_and_k(text: str, U_deg: float, k: float) -> None:
    U, kk = parse_stated_uncertainty(text)  # type: ignore[misc]
    assert U == pytest.approx(U_deg, rel=1e-12) and kk == k


@pytest.mark.parametrize(
    "text",
    [
        "0.1 degC (k = 2)",
        "0.001 deg",
        "see certificate",
        "",
        "-0.1 deg (k = 2)",
        "0.001 deg (k = 0.5)",
    ],
)
def test_wording_that_is_no_angle_with_its_k_reads_as_nothing(text: str) -> None:
    assert parse_stated_uncertainty(text) is None


def test_numbers_given_are_kept_and_k_defaults_to_two(lims) -> None:  # type: ignore[no-untyped-def]
    s = lims.standards.add_standard({**BASE, "expanded_uncertainty_deg": 0.02}, actor="admin")
    assert (s.expanded_uncertainty_deg, s.coverage_factor, s.uncertainty) == (0.02, 2.0, "")
    t = lims.standards.add_standard(
        {
            **BASE,
            "certificate_number": "C-2",
            "uncertainty": "1 arcsec (k = 2)",
            "expanded_uncertainty_deg": 0.0005,
            "coverage_factor": 2.1,
        },
        actor="admin",
    )
    # the numbers, not the remark
    assert (t.expanded_uncertainty_deg, t.coverage_factor) == (0.0005, 2.1)
    for bad in (
        {"expanded_uncertainty_deg": 0},
        {"expanded_uncertainty_deg": -1.0},
        {"expanded_uncertainty_deg": True},
        {"expanded_uncertainty_deg": 0.1, "coverage_factor": 0.5},
        {"coverage_factor": 2.0},
    ):
        with pytest.raises(InputError, match="expanded_uncertainty_deg|coverage_factor"):
            lims.standards.add_standard({**BASE, "certificate_number": "C-3", **bad}, actor="admin")


def test_a_standard_without_a_numeric_uncertainty_is_refused_at_use_by_name(lims) -> None:  # type: ignore[no-untyped-def]
    good = lims.standards.add_standard({**BASE, "uncertainty": "0.001 deg (k = 2)"}, actor="admin")
    vague = lims.standards.add_standard(
        {
            **BASE,
            "certificate_number": "C-9",
            "name": "autocollimator",
            "uncertainty": "as stated in the certificate",
        },
        actor="admin",
    )
    assert good.expanded_uncertainty_deg == 0.001 and vague.expanded_uncertainty_deg is None
    assert [s.id for s in lims.standards.usable_standards([good.id], on=ON)] == [good.id]
    with pytest.raises(
        StandardNotUsable,
        match=r"reference_standards\[1\].*autocollimator.*C-9.*no numeric uncertainty",
    ):
        lims.standards.usable_standards([good.id, vague.id], on=ON)


def test_the_migration_fills_the_numbers_where_the_text_reads(empty_engine: sa.Engine) -> None:
    upgrade(empty_engine)
    downgrade(empty_engine, "0003")
    rows = [
        ("a", "0.001 deg (k = 2)"),
        ("b", "U = 7.2 arcsec, k = 2"),
        ("c", "0.1 degC (k = 2)"),
        ("d", "ask the lab"),
    ]
    with empty_engine.begin() as conn:
        for i, (cert, text) in enumerate(rows, 1):
            conn.execute(
                sa.text(
                    "INSERT INTO reference_standards (id, name, serial, certificate_number, "
                    "certificate_sha256, calibrated_on, due_on, uncertainty, created_at, "
                    "created_by) VALUES (:id, 'std', 'S', :cert, :sha, '2026-01-10', "
                    "'2027-01-10', :text, '2026-01-10 00:00:00+00:00', 'admin')"
                ),
                {"id": i, "cert": cert, "sha": "ab" * 32, "text": text},
            )
    upgrade(empty_engine)
    with empty_engine.connect() as conn:
        got = conn.execute(
            sa.text(
                "SELECT certificate_number, expanded_uncertainty_deg, coverage_factor, uncertainty"
                " FROM reference_standards ORDER BY id"
            )
        ).all()
    assert (
        got[0][1:3] == (0.001, 2.0)
        and got[1][1] == pytest.approx(0.002, rel=1e-12)
        and got[1][2] == 2.0
    )
    assert got[2][1:3] == (None, None) and got[3][1:3] == (None, None)
    assert [g[3] for g in got] == [t for _, t in rows]  # the remark stays
