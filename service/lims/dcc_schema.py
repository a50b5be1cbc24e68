"""The DCC 3.3.0 schema, shipped with the code: validation offline, never a network fetch."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from functools import lru_cache
from pathlib import Path

import xmlschema

DCC_VERSION = "3.3.0"
DCC_NS = "https://ptb.de/dcc"
SI_NS = "https://ptb.de/si"
DSIG_NS = "http://www.w3.org/2000/09/xmldsig#"
QUDT_NS = "http://qudt.org/vocab/"
SCHEMA_DIR = Path(__file__).resolve().parent / "schemas" / f"dcc-{DCC_VERSION}"


class InvalidCertificate(ValueError):
    """A certificate that does not validate, or content that cannot be written as one."""


@lru_cache(maxsize=1)
def dcc_schema() -> xmlschema.XMLSchema:
    """DCC 3.3.0 with every import mapped to a local file: validation never goes to the network."""
    dsig = (
        Path(xmlschema.__file__).resolve().parent / "schemas" / "DSIG" / "xmldsig-core-schema.xsd"
    )
    return xmlschema.XMLSchema(
        str(SCHEMA_DIR / "dcc.xsd"),
        locations={
            SI_NS: str(SCHEMA_DIR / "SI_Format.xsd"),
            DSIG_NS: str(dsig),
            QUDT_NS: str(SCHEMA_DIR / "qudt-quantitykind-shim.xsd"),
        },
        allow="local",  # local files only, never a URL
    )


def certificate_errors(xml: bytes) -> list[str]:
    """Every reason the document is not a valid DCC 3.3.0, one line each ([] when valid)."""
    try:
        text = xml.decode("utf-8") if isinstance(xml, bytes) else xml
        # defuse: a document handed in for checking may carry entity tricks; none is ever resolved
        errors = list(
            dcc_schema().iter_errors(xmlschema.XMLResource(text, defuse="always", allow="none"))
        )
    except (ET.ParseError, xmlschema.XMLSchemaException, UnicodeDecodeError) as exc:
        return [f"not well-formed XML: {exc}"]
    return [f"{error.path or '/'}: {error.reason or error.message}" for error in errors]


def validate(xml: bytes) -> None:
    errors = certificate_errors(xml)
    if errors:
        raise InvalidCertificate(
            f"not a valid DCC {DCC_VERSION} document: {errors[0]}"
            + (f" (and {len(errors) - 1} more)" if len(errors) > 1 else "")
        )
