"""`tiltlab verify-certificate`: schema, stored hash, record and approval; a changed file or database is caught."""

from __future__ import annotations

import pytest
import sqlalchemy as sa

from service import cli
from service.config import get_settings
from service.lims.certificates import issue_certificate
from service.storage.daemon_jobs import DaemonStore
from service.storage.migrate import bootstrap
from tests.lims.test_lims_api import measured_record


@pytest.fixture
def issued(tmp_path, monkeypatch):  # type: ignore[no-untyped-def]
    monkeypatch.setenv("TILTLAB_DATA_DIR", str(tmp_path / "data"))
    for k, v in (("LAB_NAME", "Inclination Lab GmbH"), ("LAB_CITY", "Braunschweig"), ("LAB_COUNTRY_CODE", "DE")):
        monkeypatch.setenv(f"TILTLAB_{k}", v)
    get_settings.cache_clear()
    engine = bootstrap(get_settings())
    store = DaemonStore(engine)
    record = measured_record(store, started_by="alice")
    store.decide(record.id, decision="approve", meaning="approval", note="", actor="bob")
    cert = issue_certificate(store, record.id, get_settings(), actor="bob")
    path = tmp_path / f"{cert.number}.xml"
    path.write_bytes(cert.xml)
    yield engine, path
    engine.dispose()
    get_settings.cache_clear()


def test_an_issued_certificate_verifies(issued, capsys) -> None:  # type: ignore[no-untyped-def]
    _, path = issued
    assert cli.main(["verify-certificate", str(path)]) == 0
    out = capsys.readouterr().out
    assert "equals the one stored" in out and "approved by bob" in out and out.rstrip().endswith("OK")


def test_an_altered_file_fails(issued, capsys) -> None:  # type: ignore[no-untyped-def]
    _, path = issued
    path.write_bytes(path.read_bytes().replace(b"SN-4711", b"SN-4712"))
    assert cli.main(["verify-certificate", str(path)]) == 1
    assert "the file was altered" in capsys.readouterr().out
    assert cli.main(["verify-certificate", "--offline", str(path)]) == 0  # still a valid DCC, only altered


def test_an_altered_database_fails(issued, capsys) -> None:  # type: ignore[no-untyped-def]
    engine, path = issued
    with engine.begin() as conn:
        conn.exec_driver_sql("DROP TRIGGER trg_certificates_no_update")
        conn.execute(sa.text("UPDATE certificates SET xml = :x"), {"x": b"<changed/>"})
    assert cli.main(["verify-certificate", str(path)]) == 1
    assert "stored copy" in capsys.readouterr().out


def test_invalid_or_unknown_files(issued, tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    _, path = issued
    bad = tmp_path / "bad.xml"
    bad.write_bytes(path.read_bytes().replace(b'schemaVersion="3.3.0"', b'schemaVersion="3.2.1"'))
    assert cli.main(["verify-certificate", "--offline", str(bad)]) == 1
    assert "not a valid DCC 3.3.0 document" in capsys.readouterr().out
    foreign = tmp_path / "foreign.xml"
    foreign.write_bytes(path.read_bytes().replace(b"TL-", b"XX-"))
    assert cli.main(["verify-certificate", str(foreign)]) == 1
    assert "was not issued by this laboratory" in capsys.readouterr().out
    assert cli.main(["verify-certificate", str(tmp_path / "missing.xml")]) == 2
    assert "no such file" in capsys.readouterr().err
