"""The documentation a user gets stands alone: it cites the project's own docs/, never documents
outside the product, and docs/datasets.md names every dataset column the code knows."""

from __future__ import annotations

import re
from pathlib import Path

from service.io import columns

ROOT = Path(__file__).resolve().parents[2]
FOREIGN = re.compile(r"spec/[a-z]+\.md|spec §|\.\./shared|seeds/")


def _user_documents() -> list[Path]:
    docs = ROOT / "docs"
    return [ROOT / "README.md", *docs.rglob("*.md"), *docs.rglob("*.html"), *docs.rglob("*.json")]


def test_no_document_cites_files_the_user_does_not_have() -> None:
    for path in _user_documents():
        text = path.read_text(encoding="utf-8")
        found = FOREIGN.search(text)
        assert found is None, f"{path.relative_to(ROOT)} cites {found.group(0)!r}"


def test_the_contract_documents_exist_and_are_cited() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    for name in ("docs/datasets.md", "docs/models.md"):
        assert (ROOT / name).is_file()
        assert name in readme


def test_datasets_page_names_every_column() -> None:
    page = (ROOT / "docs" / "datasets.md").read_text(encoding="utf-8")
    known = {
        *columns.STAGE_DATASET,
        *columns.TARGET,
        *columns.TILT_OUTPUTS,
        *columns.ROTATION_DATASET,
        *columns.SCALE_REFERENCE,
        *columns.SCALE_DATASET,
        *columns.TURNTABLE_DATASET,
    }
    for name in sorted(known):
        assert f"`{name}`" in page or name in page, name
