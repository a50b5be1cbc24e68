"""`tiltlab verify-certificate`: schema, stored hash, record and approval; a changed file or
database is caught."""

from __future__ import annotations

import pytest
import sqlalchemy as sa

from service import cli
from service.config import get_settings
from service.lims.certificates import issue_certificate
from service.storage.migrate import bootstrap
from service.storage.store import Store
from tests.helpers.lims import PEOPLE, STANDARD, measured_record


@pytest.fixture
def issued(tmp_path, monkeypatch):  # type: ignore[no-untyped-def]
    monkeypatch.setenv("TILTLAB_DATA_DIR", str(tmp_path / "data"))
    for k, v in (
        ("LAB_NAME", "Inclination Lab GmbH"),
        ("LAB_CITY", "Braunschweig"),
        ("LAB_COUNTRY_CODE", "DE"),
    ):
        monkeypatch.setenv(f"TILTLAB_{k}", v)
    get_settings.cache_clear()
    engine = bootstrap(get_settings())
    store = Store(engine)
    store.standards.add_standard(STANDARD, actor="alice")
    record = measured_record(store, started_by="alice")
    store.approvals.decide(
        record.id,
        decision="approve",
        meaning="approval",
        note="",
        actor="bob",
        signer=PEOPLE["bob"],
    )
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
    assert (
        "equals the one stored" in out
        and "approved by Bob Example, Deputy Head of Laboratory (token bob)" in out
    )
    assert out.rstrip().endswith("OK")


def test_an_altered_file_fails(issued, capsys) -> None:  # type: ignore[no-untyped-def]
    _, path = issued
    path.write_bytes(path.read_bytes().replace(b"SN-4711", b"SN-4712"))
    assert cli.main(["verify-certificate", str(path)]) == 1
    assert "the file was altered" in capsys.readouterr().out
    # still a valid DCC, but its signature no longer verifies: the file alone shows the change
    assert cli.main(["verify-certificate", "--offline", str(path)]) == 1


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


def test_a_signed_certificate_verifies_offline_and_any_changed_byte_fails(
    issued, lab_signing_files, capsys
) -> None:  # type: ignore[no-untyped-def]
    from service.lims.certificates import verify_certificate

    _, path = issued
    good = path.read_bytes()
    _, cert = lab_signing_files
    assert cli.main(["verify-certificate", "--offline", "--signer-cert", str(cert), str(path)]) == 0
    out = capsys.readouterr().out
    assert (
        "enveloped XML signature verifies over the whole certificate" in out
        and "the certificate given" in out
    )
    # one byte changed anywhere: the declaration, the signed content, the signature, its
    # certificate, the last line
    stride = max(1, len(good) // 150)
    positions = sorted(
        {
            *range(0, len(good), stride),
            0,
            20,
            len(good) - 1,
            good.index(b"<ds:SignatureValue") + 30,
            good.index(b"<ds:X509Certificate>") + 40,
            good.index(b"<ds:DigestValue>") + 20,
        }
    )
    for i in positions:
        bad = bytearray(good)
        bad[i] = ord("x") if bad[i] != ord("x") else ord("y")
        report = verify_certificate(bytes(bad))
        assert not report.ok, (i, good[max(0, i - 20) : i + 20])
    path.write_bytes(good[:5000] + (b"1" if good[5000:5001] != b"1" else b"2") + good[5001:])
    assert cli.main(["verify-certificate", "--offline", str(path)]) == 1
    assert "FAILED" in capsys.readouterr().out


def test_the_signer_is_the_labs_own(issued, lab_signing_files, tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    from lxml import etree

    from service.lims.signature import DSIG_NS, Signer, written
    from tests.helpers.reviewer import self_signed

    _, path = issued
    other_key, other_cert = self_signed("someone else")
    (tmp_path / "other.pem").write_bytes(other_cert)
    assert (
        cli.main(
            [
                "verify-certificate",
                "--offline",
                "--signer-cert",
                str(tmp_path / "other.pem"),
                str(path),
            ]
        )
        == 1
    )
    assert "does not verify" in capsys.readouterr().out
    # re-signed by someone else after a change: valid by itself, not by the lab's certificate
    root = etree.fromstring(path.read_bytes())
    root.remove(root.find(f"{{{DSIG_NS}}}Signature"))
    unsigned = written(root)
    forged = tmp_path / "forged.xml"
    lab_signer, forger = (
        Signer(b"", lab_signing_files[1].read_bytes()),
        Signer(other_key, other_cert),
    )
    changed = unsigned.replace(b"Braunschweig", b"Wolfsburg")
    forged.write_bytes(forger(changed))  # the content still names the lab's signing certificate
    assert cli.main(["verify-certificate", "--offline", str(forged)]) == 1
    assert "names the signing certificate" in capsys.readouterr().out
    forged.write_bytes(
        forger(changed.replace(lab_signer.cert_sha256.encode(), forger.cert_sha256.encode()))
    )
    assert cli.main(["verify-certificate", "--offline", str(forged)]) == 0  # signed, by someone
    assert "CN=someone else" in capsys.readouterr().out  # and says by whom
    cert = tmp_path / "lab.pem"
    cert.write_bytes(
        etree.fromstring(path.read_bytes()).findtext(f".//{{{DSIG_NS}}}X509Certificate").encode()
    )
    lab_cert = (
        b"-----BEGIN CERTIFICATE-----\n"
        + cert.read_bytes().strip()
        + b"\n-----END CERTIFICATE-----\n"
    )
    cert.write_bytes(lab_cert)
    assert (
        cli.main(["verify-certificate", "--offline", "--signer-cert", str(cert), str(forged)]) == 1
    )
    stripped = tmp_path / "unsigned.xml"
    stripped.write_bytes(unsigned)
    assert (
        cli.main(["verify-certificate", "--offline", "--signer-cert", str(cert), str(stripped)])
        == 1
    )
    assert "carries no signature" in capsys.readouterr().out


def test_half_configured_signing_is_refused_naming_the_setting(issued, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    from service.lims.certificates import NotConfigured, signer

    monkeypatch.delenv("TILTLAB_CERTIFICATE_SIGNING_CERT")
    get_settings.cache_clear()
    with pytest.raises(NotConfigured, match="TILTLAB_CERTIFICATE_SIGNING_CERT"):
        signer(get_settings())
    monkeypatch.setenv("TILTLAB_CERTIFICATE_SIGNING_CERT", "/nonexistent/cert.pem")
    get_settings.cache_clear()
    with pytest.raises(NotConfigured, match="/nonexistent/cert.pem"):
        signer(get_settings())


def test_a_stripped_signature_does_not_read_as_ok(issued, tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    """A file whose signature was stripped is still a valid DCC document; offline it fails (nothing
    shows it is unaltered) unless --allow-unsigned, and against the database it is not the file that
    was issued."""
    from lxml import etree

    from service.lims.signature import DSIG_NS, written

    _, path = issued
    root = etree.fromstring(path.read_bytes())
    root.remove(root.find(f"{{{DSIG_NS}}}Signature"))
    stripped = tmp_path / "stripped.xml"
    stripped.write_bytes(written(root))
    assert cli.main(["verify-certificate", "--offline", str(stripped)]) == 1
    out = capsys.readouterr().out
    assert "FAILED: not signed" in out and "stripped" in out and "--allow-unsigned" in out
    assert cli.main(["verify-certificate", "--offline", "--allow-unsigned", str(stripped)]) == 0
    assert "not signed, accepted as asked (--allow-unsigned)" in capsys.readouterr().out
    assert cli.main(["verify-certificate", str(stripped)]) == 1
    assert "its signature may have been stripped" in capsys.readouterr().out
    # the issued, signed file itself
    assert cli.main(["verify-certificate", "--offline", str(path)]) == 0
    capsys.readouterr()


def test_a_laboratory_that_does_not_sign_has_its_files_vouched_for_by_its_database(
    tmp_path, monkeypatch, capsys
) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setenv("TILTLAB_DATA_DIR", str(tmp_path / "data"))
    for k, v in (
        ("LAB_NAME", "Inclination Lab GmbH"),
        ("LAB_CITY", "Braunschweig"),
        ("LAB_COUNTRY_CODE", "DE"),
    ):
        monkeypatch.setenv(f"TILTLAB_{k}", v)
    monkeypatch.delenv("TILTLAB_CERTIFICATE_SIGNING_KEY")
    monkeypatch.delenv("TILTLAB_CERTIFICATE_SIGNING_CERT")
    from service.lims import dcc

    def unsigned_issue(content, signer=None):  # type: ignore[no-untyped-def]
        assert signer is None  # the laboratory configured no signing key
        xml = dcc.build_xml(content)
        dcc.validate(xml)
        return xml

    # the suite's reviewer signs every other certificate
    monkeypatch.setattr(dcc, "issue", unsigned_issue)
    get_settings.cache_clear()
    engine = bootstrap(get_settings())
    try:
        store = Store(engine)
        store.standards.add_standard(STANDARD, actor="alice")
        record = measured_record(store, started_by="alice")
        store.approvals.decide(
            record.id,
            decision="approve",
            meaning="approval",
            note="",
            actor="bob",
            signer=PEOPLE["bob"],
        )
        cert = issue_certificate(store, record.id, get_settings(), actor="bob")
        path = tmp_path / "unsigned.xml"
        path.write_bytes(cert.xml)
        assert b"<ds:Signature" not in cert.xml
        assert cli.main(["verify-certificate", str(path)]) == 0
        assert "(the laboratory issued it unsigned)" in capsys.readouterr().out
        assert cli.main(["verify-certificate", "--offline", str(path)]) == 1
        capsys.readouterr()
    finally:
        engine.dispose()
        get_settings.cache_clear()
