"""Small helpers the reproduction reports share: Markdown tables; figures come from service.io.figures."""

from __future__ import annotations

from collections.abc import Sequence

from service.io.figures import new_figure, save_figure  # noqa: F401 - the reports' figure helpers


def md_table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    def cell(v) -> str:
        return str(v).replace("|", "\\|")

    lines = ["| " + " | ".join(cell(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)
