"""The house's figures over a source tree: what a new engineer trips over first, counted the same
way on any Python codebase (so tiltlab's `service/` can be set beside other projects measured by the
same script).

    python benchmarks/code_metrics.py [service]

Prints one line per figure:

* `dict[str, Any]` / `Mapping[str, Any]` annotations (an AST count of annotations, not of text), in
  all and per 1,000 code lines;
* code lines over 100 characters (comments and docstrings count; blank lines do not);
* files `ruff format --check` would change, and `# fmt: skip` / `# fmt: off` markers;
* one-letter assignment targets outside the mathematical i j k n m x y z t (assignments, augmented
  and annotated assignments, for-loop and with targets, comprehension variables), as a share of all
  assignment targets that are plain names;
* functions and methods with a cyclomatic complexity over 10 (radon), as a share of all;
* the median maintainability index of the modules (radon);
* public functions, methods and classes with a docstring, as a share of all.
"""

from __future__ import annotations

import ast
import json
import statistics
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

MATH_NAMES = set("ijknmxyzt")
LONG_LINE = 100


def python_files(root: Path) -> list[Path]:
    return sorted(
        p for p in root.rglob("*.py") if ".venv" not in p.parts and "build" not in p.parts
    )


def _is_str_any(node: ast.expr) -> bool:
    """`dict[str, Any]`, `Dict[str, Any]`, `Mapping[str, Any]`, `MutableMapping[str, Any]` (dotted
    or not)."""
    if not isinstance(node, ast.Subscript):
        return False
    base = node.value
    name = (
        base.attr
        if isinstance(base, ast.Attribute)
        else base.id
        if isinstance(base, ast.Name)
        else ""
    )
    if name not in {"dict", "Dict", "Mapping", "MutableMapping"}:
        return False
    args = node.slice
    if not isinstance(args, ast.Tuple) or len(args.elts) != 2:
        return False
    key, value = args.elts

    def named(n: ast.expr, want: str) -> bool:
        return (isinstance(n, ast.Name) and n.id == want) or (
            isinstance(n, ast.Attribute) and n.attr == want
        )

    return named(key, "str") and named(value, "Any")


def _annotations(tree: ast.AST) -> Iterator[ast.expr]:
    for node in ast.walk(tree):
        if isinstance(node, ast.AnnAssign):
            yield node.annotation
        elif isinstance(node, ast.arg) and node.annotation is not None:
            yield node.annotation
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.returns is not None:
            yield node.returns


def str_any_annotations(tree: ast.AST) -> int:
    """Annotations holding a `dict[str, Any]`-like type anywhere inside them (Optional, unions,
    lists of them)."""
    count = 0
    for annotation in _annotations(tree):
        count += sum(
            1 for sub in ast.walk(annotation) if isinstance(sub, ast.expr) and _is_str_any(sub)
        )
    return count


def _target_names(target: ast.expr) -> Iterator[str]:
    if isinstance(target, ast.Name):
        yield target.id
    elif isinstance(target, ast.Tuple | ast.List):
        for element in target.elts:
            yield from _target_names(element)
    elif isinstance(target, ast.Starred):
        yield from _target_names(target.value)


def assignment_targets(tree: ast.AST) -> list[str]:
    names: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign):
            for target in node.targets:
                names += _target_names(target)
        elif isinstance(
            node, ast.AugAssign | ast.AnnAssign | ast.For | ast.AsyncFor | ast.comprehension
        ):
            names += _target_names(node.target)
        elif isinstance(node, ast.withitem) and node.optional_vars is not None:
            names += _target_names(node.optional_vars)
        elif isinstance(node, ast.NamedExpr):
            names += _target_names(node.target)
    return [n for n in names if n != "_"]


def docstring_share(tree: ast.AST) -> tuple[int, int]:
    """(with a docstring, all) over public functions, methods and classes."""
    documented = total = 0
    for node in ast.walk(tree):
        if isinstance(
            node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef
        ) and not node.name.startswith("_"):
            total += 1
            documented += ast.get_docstring(node) is not None
    return documented, total


def code_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.strip()]


def radon_json(command: str, root: Path) -> dict[str, object]:
    out = subprocess.run(
        [sys.executable, "-m", "radon", command, "-j", str(root)],
        capture_output=True,
        text=True,
        check=True,
    )
    parsed: dict[str, object] = json.loads(out.stdout)
    return parsed


def main() -> None:
    root = Path(sys.argv[1] if len(sys.argv) > 1 else "service")
    files = python_files(root)
    lines = str_any = long_lines = fmt_skips = documented = public = 0
    targets: list[str] = []
    for path in files:
        text = path.read_text(encoding="utf-8")
        tree = ast.parse(text)
        body = code_lines(text)
        lines += len(body)
        long_lines += sum(len(line) > LONG_LINE for line in body)
        fmt_skips += text.count("# fmt: skip") + text.count("# fmt: off")
        str_any += str_any_annotations(tree)
        targets += assignment_targets(tree)
        d, t = docstring_share(tree)
        documented, public = documented + d, public + t
    one_letter = [n for n in targets if len(n) == 1 and n not in MATH_NAMES]

    fmt = subprocess.run(
        [
            sys.executable,
            "-m",
            "ruff",
            "format",
            "--check",
            "--output-format",
            "concise",
            str(root),
        ],
        capture_output=True,
        text=True,
    )
    would_change = sum(1 for line in fmt.stdout.splitlines() if "File would be reformatted" in line)

    blocks = [
        b
        for entries in radon_json("cc", root).values()
        if isinstance(entries, list)
        for b in _flatten(entries)
        if b.get("type") in ("function", "method")
    ]
    complex_blocks = [b for b in blocks if int(b["complexity"]) > 10]
    indices = [
        float(v["mi"]) for v in radon_json("mi", root).values() if isinstance(v, dict) and "mi" in v
    ]

    print(f"tree: {root} ({len(files)} files, {lines:,} non-blank lines)")
    print(
        f"dict[str, Any] / Mapping[str, Any] annotations: {str_any} ({1000 * str_any / lines:.1f} "
        "per 1,000 lines)"
    )
    print(f"lines over {LONG_LINE} characters: {long_lines} ({100 * long_lines / lines:.1f} %)")
    print(
        f"ruff format --check: {would_change} of {len(files)} files would change; {fmt_skips} fmt: "
        "skip/off markers"
    )
    print(
        f"one-letter assignment targets outside {' '.join(sorted(MATH_NAMES))}: {len(one_letter)} "
        f"of {len(targets)}"
        f" ({100 * len(one_letter) / max(len(targets), 1):.1f} %)"
    )
    print(
        f"functions with cyclomatic complexity > 10: {len(complex_blocks)} of {len(blocks)}"
        f" ({100 * len(complex_blocks) / max(len(blocks), 1):.1f} %)"
    )
    print(f"maintainability index, median over modules: {statistics.median(indices):.0f}")
    print(
        f"public functions and classes with a docstring: {documented} of {public}"
        f" ({100 * documented / max(public, 1):.0f} %)"
    )


def _flatten(entries: list[dict[str, object]]) -> Iterator[dict[str, object]]:
    """radon's blocks with a class's methods listed as blocks of their own (radon nests them)."""
    for entry in entries:
        if entry.get("type") == "class":
            methods = entry.get("methods")
            if isinstance(methods, list):
                yield from _flatten(methods)
        else:
            yield entry
            closures = entry.get("closures")
            if isinstance(closures, list):
                yield from _flatten(closures)


if __name__ == "__main__":
    main()
