"""Independent machine checks of an issued certificate with the tools a reviewer runs: libxml2's
`xmllint` against the DCC 3.3.0 schema (the package's copy, its imports laid out as the schema names
them, the D-SI's QUDT import mapped by an XML catalog to the shipped stand-in; no network) and
`xmlsec1 --verify` of the enveloped signature against the laboratory's certificate. Debian's
libxml2-utils and xmlsec1 packages (.ci/run installs them)."""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest
import xmlschema

from service.lims.dcc_schema import SCHEMA_DIR

QUDT = "https://www.ptb.de/si/v2.2.0/qudt/quantitykind.xsd"  # what D-SI 2.2.0 imports


def _tool(name: str) -> str:
    found = shutil.which(name)
    if found is None:
        pytest.skip(
            f"{name} is not installed (Debian: apt-get install "
            f"{'libxml2-utils' if name == 'xmllint' else name})"
        )
    return found


def xmllint_errors(xml: bytes) -> list[str]:
    """xmllint's complaints about the document against the schema ([] when it says it validates)."""
    xmllint = _tool("xmllint")
    with tempfile.TemporaryDirectory(prefix="tiltlab-xmllint-") as tmp:
        here = Path(tmp)
        (here / "si").mkdir()
        (here / "d-sig").mkdir()
        shutil.copy(SCHEMA_DIR / "dcc.xsd", here / "dcc.xsd")
        shutil.copy(SCHEMA_DIR / "SI_Format.xsd", here / "si" / "SI_Format.xsd")
        shutil.copy(
            Path(xmlschema.__file__).parent / "schemas" / "DSIG" / "xmldsig-core-schema.xsd",
            here / "d-sig" / "xmldsig-core-schema.xsd",
        )
        shim = (SCHEMA_DIR / "qudt-quantitykind-shim.xsd").resolve().as_uri()
        (here / "catalog.xml").write_text(
            '<?xml version="1.0"?>\n<catalog xmlns="urn:oasis:names:tc:entity:xmlns:xml:catalog">\n'
            f'  <uri name="{QUDT}" uri="{shim}"/>\n  <system systemId="{QUDT}" '
            f'uri="{shim}"/>\n</catalog>\n'
        )
        (here / "certificate.xml").write_bytes(xml)
        run = subprocess.run(
            [
                xmllint,
                "--noout",
                "--nonet",
                "--schema",
                str(here / "dcc.xsd"),
                str(here / "certificate.xml"),
            ],
            capture_output=True,
            text=True,
            timeout=120,
            env={"XML_CATALOG_FILES": str(here / "catalog.xml"), "PATH": "/usr/bin:/bin"},
        )
    if run.returncode == 0 and "validates" in run.stderr:
        return []
    return [line for line in run.stderr.splitlines() if line.strip()] or [
        f"xmllint exited {run.returncode}"
    ]


def xmlsec1_verifies(xml: bytes, signer_cert_pem: Path) -> bool:
    """Whether `xmlsec1 --verify` accepts the enveloped signature, made with the key of
    `signer_cert_pem`."""
    xmlsec1 = _tool("xmlsec1")
    with tempfile.TemporaryDirectory(prefix="tiltlab-xmlsec1-") as tmp:
        path = Path(tmp) / "certificate.xml"
        path.write_bytes(xml)
        run = subprocess.run(
            [xmlsec1, "--verify", "--pubkey-cert-pem", str(signer_cert_pem), str(path)],
            capture_output=True,
            text=True,
            timeout=120,
        )
    return run.returncode == 0 and "OK" in run.stderr
