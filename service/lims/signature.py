"""The certificate's enveloped XML signature (XMLDSig, RSA or ECDSA with SHA-256): the file itself
is tamper-evident.

The laboratory configures its key and X.509 certificate (TILTLAB_CERTIFICATE_SIGNING_KEY and
TILTLAB_CERTIFICATE_SIGNING_CERT, PEM files). The signature covers the whole certificate (the
root element, canonicalised) and carries the signing certificate, so its holder can check it
offline; `check` also requires the file to be byte for byte the form it was written in, so that
a change outside the signed element (the XML declaration, the last line) is found as well.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import serialization
from lxml import etree
from signxml.exceptions import InvalidInput, InvalidSignature
from signxml.signer import XMLSigner
from signxml.verifier import XMLVerifier

from service.lims.dcc import SIGNING_CERT_NAME
from service.lims.dcc_schema import DCC_NS, DSIG_NS

DECLARATION = b'<?xml version="1.0" encoding="UTF-8"?>\n'


class SigningNotConfigured(ValueError):
    """The key or certificate the lab configured cannot be read or do not belong together."""


@dataclass(frozen=True)
class Signer:
    key_pem: bytes
    cert_pem: bytes

    @property
    def cert_sha256(self) -> str:
        """What the signed content names as its signer (the DER certificate's SHA-256)."""
        der = x509.load_pem_x509_certificate(self.cert_pem).public_bytes(serialization.Encoding.DER)
        return hashlib.sha256(der).hexdigest()

    def __call__(self, xml: bytes) -> bytes:
        """The document with its enveloped signature as the root element's last child."""
        root = etree.fromstring(xml, parser=_parser())
        signed = XMLSigner(c14n_algorithm="http://www.w3.org/TR/2001/REC-xml-c14n-20010315").sign(
            root, key=self.key_pem, cert=self.cert_pem.decode("ascii")
        )
        return written(signed)


def _parser() -> etree.XMLParser:
    # no entities, no network, no huge trees: a file handed in for checking is not trusted
    return etree.XMLParser(
        resolve_entities=False, no_network=True, huge_tree=False, remove_blank_text=False
    )


def written(root: etree._Element) -> bytes:
    """The one byte form a signed certificate is written in: the declaration, the root, a
    newline."""
    body: bytes = etree.tostring(root, encoding="UTF-8")
    return DECLARATION + body + b"\n"


def load_signer(key_path: str | Path, cert_path: str | Path) -> Signer:
    """The lab's signer; refused (naming the file) when the files are unreadable or the key is not
    the cert's."""
    try:
        key_pem, cert_pem = Path(key_path).read_bytes(), Path(cert_path).read_bytes()
    except OSError as exc:
        raise SigningNotConfigured(f"{exc.filename}: cannot read: {exc.strerror}") from None
    try:
        key = serialization.load_pem_private_key(key_pem, password=None)
        cert = x509.load_pem_x509_certificate(cert_pem)
    except (ValueError, TypeError) as exc:
        raise SigningNotConfigured(
            f"{key_path} / {cert_path}: not a PEM private key and X.509 certificate: {exc}"
        ) from None
    pub = serialization.PublicFormat.SubjectPublicKeyInfo
    if key.public_key().public_bytes(
        serialization.Encoding.DER, pub
    ) != cert.public_key().public_bytes(serialization.Encoding.DER, pub):
        raise SigningNotConfigured(f"{key_path} is not the key of the certificate {cert_path}")
    return Signer(key_pem, cert_pem)


@dataclass
class SignatureCheck:
    signed: bool
    ok: bool
    detail: str
    signer: str = ""
    cert_sha256: str = ""


def check(xml: bytes, trusted_cert_pem: bytes | None = None) -> SignatureCheck:
    """Whether the file carries a valid enveloped signature over its whole content, made by the
    certificate it carries (or by `trusted_cert_pem` when given), and is byte for byte as it was
    written."""
    try:
        root = etree.fromstring(xml, parser=_parser())
    except etree.XMLSyntaxError as exc:
        return SignatureCheck(False, False, f"not well-formed XML: {exc}")
    sigs = root.findall(f"{{{DSIG_NS}}}Signature")
    if not sigs:
        return SignatureCheck(False, False, "the certificate carries no signature")
    if len(sigs) > 1 or root[-1] is not sigs[0]:
        return SignatureCheck(
            True, False, "the signature is not the certificate's one enveloped signature"
        )
    embedded = sigs[0].findtext(f".//{{{DSIG_NS}}}X509Certificate")
    if not embedded and trusted_cert_pem is None:
        return SignatureCheck(True, False, "the signature carries no certificate to check it with")
    cert_pem = trusted_cert_pem or (
        b"-----BEGIN CERTIFICATE-----\n"
        + "".join(embedded.split()).encode()
        + b"\n-----END CERTIFICATE-----\n"
    )
    return _check_signed(xml, root, cert_pem)


def _named_signing_certs(signed_root: etree._Element) -> list[str | None]:
    """The SHA-256s the signed content names as the certificate that signs it (one, when it is
    right)."""
    return [
        identification.findtext(f"{{{DCC_NS}}}value")
        for identification in signed_root.iter(f"{{{DCC_NS}}}identification")
        if (identification.findtext(f"{{{DCC_NS}}}name/{{{DCC_NS}}}content") or "")
        == SIGNING_CERT_NAME
    ]


def _check_signed(xml: bytes, root: etree._Element, cert_pem: bytes) -> SignatureCheck:
    """The one enveloped signature verifies with the certificate, covers the whole certificate, the
    file is as it was written and its signed content names that certificate as its signer."""
    try:
        cert = x509.load_pem_x509_certificate(cert_pem)
        result = XMLVerifier().verify(xml, x509_cert=cert, parser=_parser())
    except (InvalidSignature, InvalidInput, ValueError) as exc:
        return SignatureCheck(True, False, f"the signature does not verify: {exc}")
    signed_root = result.signed_xml if not isinstance(result, list) else None
    if signed_root is None or signed_root.tag != root.tag:
        return SignatureCheck(True, False, "the signature does not cover the whole certificate")
    if written(root) != xml:
        return SignatureCheck(
            True, False, "the file differs from the signed form outside the signed element"
        )
    fingerprint = hashlib.sha256(cert.public_bytes(serialization.Encoding.DER)).hexdigest()
    named = _named_signing_certs(signed_root)
    if named != [fingerprint]:
        return SignatureCheck(
            True,
            False,
            f"the signed content names the signing certificate {named or 'nowhere'}, "
            f"not the one the signature carries ({fingerprint})",
        )
    return SignatureCheck(
        True,
        True,
        "enveloped XML signature verifies over the whole certificate",
        cert.subject.rfc4514_string(),
        fingerprint,
    )
