"""What a DCC reviewer checks in every certificate the tests issue, with independent tools: PTB's
D-SI unit parser (dsiunits), the shipped DCC 3.3.0 schema, the parameters' covariance, GUM 7.2.6
rounding, the item's identity, and (when the certificate is signed) its signature."""

from __future__ import annotations

import datetime as dt
import re
import warnings
import xml.etree.ElementTree as ET

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import NameOID
from dsi_unit import DsiUnit

from service.lims import dcc, signature

NS = {"dcc": dcc.DCC_NS, "si": dcc.SI_NS, "ds": dcc.DSIG_NS}
SI = "{" + dcc.SI_NS + "}"
# a number without an uncertainty of its own: no float artefacts (0.6126699999999999)
MAX_PLAIN_DIGITS = 6


def significant(text: str) -> int:
    mant = re.split(r"[eE]", text.strip().lstrip("+-"))[0].replace(".", "").lstrip("0")
    return len(mant.rstrip("0")) if "." not in text and "e" not in text.lower() else len(mant) or 1


def decimals(text: str) -> int:
    return len(text.split(".")[1]) if "." in text else 0


def units_of(root: ET.Element) -> list[str]:
    out = [e.text or "" for e in root.iter(SI + "unit")]
    for e in root.iter(SI + "unitXMLList"):
        out += (e.text or "").split()
    return out


def self_signed(common_name: str) -> tuple[bytes, bytes]:
    """A new RSA key and a self-signed X.509 certificate for it (PEM), valid for a year from now."""
    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    now = dt.datetime.now(dt.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(days=1))
        .not_valid_after(now + dt.timedelta(days=365))
        .sign(key, hashes.SHA256())
    )
    return (
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        ),
        cert.public_bytes(serialization.Encoding.PEM),
    )


def problems(xml: bytes, signed_by: bytes | None = None) -> list[str]:
    """Every reason a reviewer would refuse the certificate ([] when none); with `signed_by` (a PEM
    certificate) the file must carry a valid signature made with it."""
    found = [f"schema: {e}" for e in dcc.certificate_errors(xml)]
    if signed_by is not None:
        sig = signature.check(xml, signed_by)
        if not sig.ok:
            found.append(f"signature: {sig.detail}")
    root = ET.fromstring(xml)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for u in set(units_of(root)):
            parsed = DsiUnit(u)
            if not parsed.valid or parsed.warnings:
                found.append(f"unit {u!r} is not valid D-SI: {parsed.warnings}")
    # expanded uncertainties: U to two significant digits, the value to the same decimal place
    for real in root.iter(SI + "real"):
        u = real.find("si:measurementUncertaintyUnivariate/si:expandedMU/si:valueExpandedMU", NS)
        v = real.find("si:value", NS)
        assert v is not None
        if u is not None:
            if significant(u.text or "") > 2 or decimals(v.text or "") != decimals(u.text or ""):
                found.append(
                    f"{real.findtext('si:label', '', NS)}: value {v.text} with U {u.text} is not "
                    "GUM-rounded"
                )
        elif significant(v.text or "") > MAX_PLAIN_DIGITS:
            found.append(
                f"{real.findtext('si:label', '', NS)}: {v.text} carries more digits than it can "
                "mean"
            )
    for lst in root.iter(SI + "realListXMLList"):
        values = (lst.findtext("si:valueXMLList", "", NS)).split()
        us = (
            lst.findtext(
                "si:measurementUncertaintyUnivariateXMLList/si:expandedMUXMLList/si:valueExpandedMUXMLList",
                "",
                NS,
            )
        ).split()
        for i, v in enumerate(values):
            if us:
                if significant(us[i]) > 2 or decimals(v) != decimals(us[i]):
                    found.append(
                        f"{lst.findtext('si:labelXMLList', '', NS)}[{i}]: {v} ± {us[i]} is not "
                        "GUM-rounded"
                    )
            elif significant(v) > MAX_PLAIN_DIGITS:
                found.append(
                    f"{lst.findtext('si:labelXMLList', '', NS)}[{i}]: {v} carries more digits than "
                    "it can mean"
                )
    for tag in ("coverageFactor", "coverageFactorXMLList", "valueXMLList"):
        for e in root.iter(SI + tag):
            for t in (e.text or "").split():
                if significant(t) > MAX_PLAIN_DIGITS:
                    found.append(f"{tag} {t} carries more digits than it can mean")
    # the parameters' covariance beside their expanded uncertainties
    for result in root.iter("{" + dcc.DCC_NS + "}result"):
        fitted = [
            q
            for q in result.iter("{" + dcc.DCC_NS + "}quantity")
            if q.get("refType") == "tiltlab_modelParameter"
            and q.find("si:real/si:measurementUncertaintyUnivariate", NS) is not None
        ]
        matrix = result.find(".//si:ellipsoidalRegionMUXMLList/si:covarianceMatrixXMLList", NS)
        if fitted and (matrix is None or len(matrix.findall("si:columnXMLList", NS)) < len(fitted)):
            found.append(
                f"{len(fitted)} parameters with uncertainties but no covariance matrix of them"
            )
    # the distribution named truthfully: not 'normal' beside a coverage factor that is Student's t
    for mu in root.iter(SI + "expandedMU"):
        if (
            mu.findtext("si:distribution", "", NS) == "normal"
            and mu.findtext("si:coverageProbability", "", NS) == "0.95"
            and abs(float(mu.findtext("si:coverageFactor", "0", NS)) - 1.96) > 0.005
        ):
            found.append(
                f"distribution 'normal' beside k = {mu.findtext('si:coverageFactor', '', NS)}"
            )
    # the item by its serial, never a port or a role
    ids = [
        i.findtext("dcc:value", "", NS)
        for i in root.findall(
            "dcc:administrativeData/dcc:items/dcc:item/dcc:identifications/dcc:identification", NS
        )
    ]
    if not ids:
        found.append("the item has no identification")
    for v in ids:
        if re.search(r"/dev/|address 0x|_sensor|\bport\b|pty", v):
            found.append(f"the item is identified by {v!r}, a port or role")
    # every refType of our own is defined in the file
    defined = {d.get("refType") for d in root.iter("{" + dcc.DCC_NS + "}refTypeDefinition")}
    used = {
        t for e in root.iter() for t in (e.get("refType") or "").split() if t.startswith("tiltlab_")
    }
    if used - defined:
        found.append(f"refTypes without a definition: {sorted(used - defined)}")
    return found
