"""Small helpers the reproduction reports share: Markdown tables; figures come from
service.io.figures."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TypeVar

from service.io.figures import new_figure, save_figure

# the reports' figure helpers come from here too
__all__ = ["md_table", "new_figure", "of_kind", "save_figure"]

ScenarioT = TypeVar("ScenarioT")


def of_kind(scenario: object, kind: type[ScenarioT]) -> ScenarioT:
    """The scenario as the kind the report runs on: a preset of another kind is refused, not
    half-run."""
    if not isinstance(scenario, kind):
        raise TypeError(f"this report runs on a {kind.__name__}, not a {type(scenario).__name__}")
    return scenario


def md_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    def cell(v: object) -> str:
        return str(v).replace("|", "\\|")

    lines = [
        "| " + " | ".join(cell(heading) for heading in header) + " |",
        "|" + "---|" * len(header),
    ]
    lines += ["| " + " | ".join(cell(value) for value in row) + " |" for row in rows]
    return "\n".join(lines)
