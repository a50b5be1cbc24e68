"""LIMS storage tests run on SQLite and PostgreSQL, with the storage tests' fixtures
(tests/conftest.py)."""

from __future__ import annotations

import pytest

from service.storage.store import Store


@pytest.fixture
def lims(engine) -> Store:  # type: ignore[no-untyped-def]
    """The store the daemon uses: the lab's records, jobs, tokens and the LIMS tables."""
    return Store(engine)


@pytest.fixture(scope="session")
def lab_signing_files(tmp_path_factory):  # type: ignore[no-untyped-def]
    """A self-signed key and certificate as a lab would configure them (PEM files)."""
    from tests.helpers.reviewer import self_signed

    key_pem, cert_pem = self_signed("Inclination Lab certificate signing")
    where = tmp_path_factory.mktemp("signing")
    (where / "key.pem").write_bytes(key_pem)
    (where / "cert.pem").write_bytes(cert_pem)
    return where / "key.pem", where / "cert.pem"


@pytest.fixture(autouse=True)
def reviewed_certificates(monkeypatch, lab_signing_files):  # type: ignore[no-untyped-def]
    """Every certificate a LIMS test issues is signed with the lab's key (configured as a lab would)
    and checked as a reviewer would (tests/helpers/reviewer.py), its signature included."""
    from service.lims import dcc
    from service.lims.signature import load_signer
    from tests.helpers.reviewer import problems

    key, cert = lab_signing_files
    monkeypatch.setenv("TILTLAB_CERTIFICATE_SIGNING_KEY", str(key))
    monkeypatch.setenv("TILTLAB_CERTIFICATE_SIGNING_CERT", str(cert))
    issue, lab_signer = dcc.issue, load_signer(key, cert)

    def reviewed(content, signer=None):  # type: ignore[no-untyped-def]
        xml = issue(content, signer or lab_signer)
        found = problems(xml, signed_by=cert.read_bytes())
        assert not found, found
        return xml

    monkeypatch.setattr(dcc, "issue", reviewed)
