"""The one way datasets come in and go out: CSV files as docs/datasets.md describes them.

Reading validates every cell the command uses and names file, row and column on refusal.
Writing goes to a temporary file in the target's folder and is renamed into place, so a
failure never leaves a half-written file. Unknown extra columns are kept as text and passed
through to outputs.
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
from numpy.typing import NDArray

from service.errors import InputError
from service.io.columns import INTEGER_COLUMNS

KINDS = ("stage", "rotation", "scale", "turntable")
SINE_MARGIN = 1e-3


def _range_for(kind: str, col: str) -> tuple[float, float] | None:
    if col in ("sx", "sy", "sz"):
        return (-1.0 - SINE_MARGIN, 1.0 + SINE_MARGIN)
    if col == "temp_c":
        return (-50.0, 150.0)
    if kind == "stage" and col.endswith("_deg"):
        return (-90.0, 90.0)
    if col in ("target_x_deg", "target_y_deg"):
        return (-90.0, 90.0)
    if col == "theta_ref_deg":
        return (-360.0, 360.0)
    if col == "azimuth_deg":
        return (-360.0, 720.0)
    return None


@dataclass
class Dataset:
    """A validated table: numeric columns the command uses, everything else as text."""

    source: str
    kind: str
    header: list[str]
    text: dict[str, list[str]]
    numeric: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    lines: list[int] = field(default_factory=list)  # line of the file each data row starts on

    def where(self, row: int, col: str) -> str:
        """File, row (1-based, data rows only) and column, as every refusal names them."""
        return _where(self.source, row, col, self.lines[row - 1] if self.lines else None)

    @property
    def n_rows(self) -> int:
        return len(next(iter(self.text.values()))) if self.text else 0

    def __getitem__(self, col: str) -> NDArray[np.float64]:
        return self.numeric[col]

    def arrays(self) -> dict[str, NDArray[np.float64]]:
        return dict(self.numeric)

    def passthrough(self, exclude: Iterable[str] = ()) -> dict[str, list[str]]:
        ex = set(exclude)
        return {name: self.text[name] for name in self.header if name not in ex}


def _where(source: str, row: int, col: str, line: int | None = None) -> str:
    return f"{source}, row {row} (line {row + 1 if line is None else line}), column {col!r}"


# A number as the contract writes it: ASCII digits, '.' as the decimal mark, optional exponent.
# (float() alone would also take '1_000', non-ASCII digits and 'nan'/'inf'.)
# Only spaces and tabs around a cell are padding; any other character (a control code, a
# Unicode space) is part of the cell and makes it not a number, rather than being dropped.
_BLANK = " \t"
_NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_DECIMAL_COMMA = re.compile(r"[+-]?[0-9]*,[0-9]+")
_NON_FINITE = {"nan", "inf", "infinity"}


def _decode(source: str, data: bytes) -> str:
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise InputError(
            f"{source}: the file is UTF-16 text; save it as CSV in UTF-8 (comma-separated)"
        )
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        start = exc.start + (3 if data.startswith(b"\xef\xbb\xbf") else 0)
        line = data[:start].count(b"\n") + 1
        raise InputError(
            f"{source}, line {line}: byte 0x{data[start]:02x} is not UTF-8 text; "
            "save the file as CSV in UTF-8"
        ) from None


def _separator_error(source: str, header_cell: str) -> InputError | None:
    for sep, name in ((";", "semicolon"), ("\t", "tab")):
        if sep in header_cell:
            return InputError(
                f"{source}, line 1: the header is separated by {name}s ({header_cell[:40]!r}...); "
                "the separator must be a comma (',') and the decimal mark a point ('.')"
            )
    return None


def read_dataset(
    path: str | Path,
    kind: str,
    required: Sequence[str | tuple[str, ...]] = (),
    optional: Sequence[str] = (),
    *,
    max_rows: int | None = None,
) -> Dataset:
    """Read and validate a dataset.

    `required` items are column names or tuples of alternatives (the first present is used,
    e.g. ("ref_arcsec", "ref_deg")). `optional` columns are validated when present; the two axes of
    a sensor (`*_x_*` and `*_y_*`) go together: one without the other is refused, naming the missing
    one. With `max_rows`, a file of more data rows is refused before it is read (counted line by
    line, in constant memory).
    """
    source = str(path)
    if max_rows is not None:
        _refuse_more_rows_than(source, Path(path), max_rows)
    rows, lines = _csv_rows(source, _read_bytes(source, Path(path)))
    header = _checked_header(source, rows)
    body, lines = rows[1:], lines[1:]
    if not body:
        raise InputError(f"{source}: no data rows under the header")
    _check_row_lengths(source, body, lines, header)
    text = {name: [row[j].strip(_BLANK) for row in body] for j, name in enumerate(header)}
    ds = Dataset(source, kind, header, text, lines=lines)
    for col in _columns_used(source, kind, text, required, optional):
        ds.numeric[col] = _numeric_column(ds, col)
    return ds


def _read_bytes(source: str, path: Path) -> bytes:
    """The file's bytes, or one line saying why they cannot be read."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{source}: no such file") from None
    except OSError as exc:
        raise InputError(f"{source}: cannot read: {exc.strerror or exc}") from None


def _csv_rows(source: str, data: bytes) -> tuple[list[list[str]], list[int]]:
    """The CSV's rows that are not blank, and the line of the file each starts on."""
    rows: list[list[str]] = []
    lines: list[int] = []  # the line each kept row starts on
    reader = csv.reader(io.StringIO(_decode(source, data), newline=""))
    try:
        start = 1
        for row in reader:
            if any(cell.strip(_BLANK) for cell in row):
                rows.append(row)
                lines.append(start)
            start = reader.line_num + 1
    except csv.Error as exc:
        raise InputError(f"{source}, line {reader.line_num}: cannot read as CSV: {exc}") from None
    return rows, lines


def _checked_header(source: str, rows: list[list[str]]) -> list[str]:
    """The header's column names: comma-separated, none empty, none twice."""
    if not rows:
        raise InputError(f"{source}: empty file (a header row is required)")
    if len(rows[0]) == 1 and (err := _separator_error(source, rows[0][0])):
        raise err
    header = [cell.strip(_BLANK) for cell in rows[0]]
    if any(not name for name in header):
        raise InputError(
            f"{source}: header has an empty column name at position {header.index('') + 1}"
        )
    dup = sorted({name for name in header if header.count(name) > 1})
    if dup:
        raise InputError(f"{source}: column {dup[0]!r} appears more than once in the header")
    return header


def _check_row_lengths(
    source: str, body: list[list[str]], lines: list[int], header: list[str]
) -> None:
    """Every data row has as many cells as the header."""
    for i, row in enumerate(body, start=1):
        if len(row) != len(header):
            raise InputError(
                f"{source}, row {i} (line {lines[i - 1]}): {len(row)} cells where the header has "
                f"{len(header)}"
            )


def _columns_used(
    source: str,
    kind: str,
    text: dict[str, list[str]],
    required: Sequence[str | tuple[str, ...]],
    optional: Sequence[str],
) -> list[str]:
    """The columns to read as numbers: each required one (the first alternative present), then the
    optional ones present."""
    use: list[str] = []
    for item in required:
        alts = (item,) if isinstance(item, str) else tuple(item)
        found = next((alt for alt in alts if alt in text), None)
        if found is None:
            names = " or ".join(repr(alt) for alt in alts)
            raise InputError(f"{source}: missing required column {names} for kind {kind!r}")
        use.append(found)
    _check_axis_pairs(source, text, optional)
    use += [col for col in optional if col in text and col not in use]
    return use


def _check_axis_pairs(source: str, text: dict[str, list[str]], optional: Sequence[str]) -> None:
    """A sensor's two axes go together: one alone is a column lost, not an option left out."""
    for col in optional:
        partner = _partner(col)
        if col in text and partner is not None and partner in optional and partner not in text:
            raise InputError(
                f"{source}: has column {col!r} but not {partner!r}: the two axes of a sensor go "
                f"together; add {partner!r}, or leave out both"
            )


def _partner(col: str) -> str | None:
    """The other axis's column of a per-axis column (`meas_x_deg` <-> `meas_y_deg`), or None."""
    for axis, other in (("_x_", "_y_"), ("_y_", "_x_")):
        if axis in col:
            return col.replace(axis, other, 1)
    return None


def _refuse_more_rows_than(source: str, path: Path, max_rows: int) -> None:
    """InputError when the file has more than `max_rows` data rows (non-blank lines under the
    header)."""
    try:
        with path.open("rb") as file:
            rows = -1  # the header
            for line in file:
                if line.strip():
                    rows += 1
                    if rows > max_rows:
                        break
    except FileNotFoundError:
        raise InputError(f"{source}: no such file") from None
    except OSError as exc:
        raise InputError(f"{source}: cannot read: {exc.strerror or exc}") from None
    if rows > max_rows:
        raise InputError(
            f"{source}: more than {max_rows:,} data rows; calibrate fits at most {max_rows:,} "
            "(--max-rows). A calibration run has one row per settled point: average the raw "
            "readings of each point first, or raise --max-rows (docs/datasets.md says what a "
            "fit of many rows costs)"
        )


def _numeric_column(ds: Dataset, col: str) -> NDArray[np.float64]:
    cells = ds.text[col]
    values = np.empty(len(cells))
    for i, cell in enumerate(cells):
        if not _NUMBER.fullmatch(cell):
            raise _not_a_number(ds, col, i, cell)
        value = float(cell)
        if not math.isfinite(value):
            raise InputError(f"{ds.where(i + 1, col)}: {cell!r} is not a finite number")
        values[i] = value
    _check_range(ds, col, values)
    _check_column_rules(ds, col, values)
    return values


def _not_a_number(ds: Dataset, col: str, i: int, cell: str) -> InputError:
    """Why a cell is not a number: empty (in every row?), not finite, or with a decimal comma."""
    if cell == "":
        if not any(ds.text[col]):
            return InputError(
                f"{ds.where(i + 1, col)}: empty cell (the column is empty in every row)"
            )
        return InputError(f"{ds.where(i + 1, col)}: empty cell")
    if cell.lower().lstrip("+-") in _NON_FINITE:
        return InputError(f"{ds.where(i + 1, col)}: {cell!r} is not a finite number")
    hint = " (the decimal mark must be '.')" if _DECIMAL_COMMA.fullmatch(cell) else ""
    return InputError(f"{ds.where(i + 1, col)}: {cell!r} is not a number{hint}")


def _check_range(ds: Dataset, col: str, values: NDArray[np.float64]) -> None:
    """The column's values within the range its quantity can have (a tilt within ±90 deg, ...)."""
    rng = _range_for(ds.kind, col)
    if rng is not None:
        lo, hi = rng
        bad = np.flatnonzero((values < lo) | (values > hi))
        if bad.size:
            i = int(bad[0])
            unit = (
                " (no tilt in degrees is beyond ±90: is the column in another unit?)"
                if col.endswith("_deg") and hi == 90.0
                else ""
            )
            raise InputError(
                f"{ds.where(i + 1, col)}: {ds.text[col][i]} is outside [{lo:g}, {hi:g}]{unit}"
            )


def _check_column_rules(ds: Dataset, col: str, values: NDArray[np.float64]) -> None:
    """The rules of particular columns: a direction is -1, 0 or 1; t_s never decreases; point
    and cycle are whole numbers of 0 or more."""
    cells = ds.text[col]
    if col.startswith("dir_"):
        bad = np.flatnonzero(~np.isin(values, (-1.0, 0.0, 1.0)))
        if bad.size:
            i = int(bad[0])
            raise InputError(f"{ds.where(i + 1, col)}: {cells[i]} is not one of -1, 0, 1")
    if col == "t_s":
        dec = np.flatnonzero(np.diff(values) < 0)
        if dec.size:
            i = int(dec[0]) + 1
            raise InputError(
                f"{ds.where(i + 1, col)}: {cells[i]} is earlier than the row before "
                f"({cells[i - 1]}); t_s must not decrease"
            )
    if col in ("point", "cycle"):
        bad = np.flatnonzero((values != np.round(values)) | (values < 0))
        if bad.size:
            i = int(bad[0])
            raise InputError(
                f"{ds.where(i + 1, col)}: {cells[i]} is not a non-negative whole number"
            )


_INTEGER_COLUMNS = INTEGER_COLUMNS


# Decimals an output column is written with, by its unit: 1/100 of the finest resolution that
# quantity has on any bench here (stage pulse 0.0005°, sensor resolution 0.2″, sines of 1e-8),
# so rounding never shows in a result and no digit beyond the instruments' is invented.
DECIMALS_BY_SUFFIX = (("_deg", 7), ("_arcsec", 4), ("_rad", 9))
DECIMALS_BY_COLUMN = {"sx": 10, "sy": 10, "sz": 10}
# columns in other units (readings in the instrument's unit, times, temperatures)
SIGNIFICANT_DIGITS = 10


def format_value(col: str, v: str | float, *, exact: bool = False) -> str:
    """A cell as text, with the digits its unit merits (docs/models.md, "Digits").

    `exact`: the shortest text that reads back to the same double, for exports whose purpose is
    an identical re-fit (a record's stored points), not a result for people.
    """
    if isinstance(v, str):
        return v
    number = float(v)
    if col in _INTEGER_COLUMNS and number == round(number):
        return str(int(round(number)))
    if exact or not math.isfinite(number):
        return repr(number)
    decimals = _decimals(col)
    if decimals is None:
        text = f"{number:.{SIGNIFICANT_DIGITS}g}"
        return "0" if text == "-0" else text
    text = f"{number:.{decimals}f}".rstrip("0")
    text = text + "0" if text.endswith(".") else text
    return "0.0" if text in ("-0.0", "0.0") else text


def _decimals(col: str) -> int | None:
    """The decimals a column is written with, by its name or else its unit's suffix; None for a
    column in another unit (written to SIGNIFICANT_DIGITS)."""
    decimals = DECIMALS_BY_COLUMN.get(col)
    if decimals is None:
        decimals = next(
            (digits for suffix, digits in DECIMALS_BY_SUFFIX if col.endswith(suffix)), None
        )
    return decimals


@contextmanager
def about(path: object) -> Iterator[None]:
    """Name the file a refusal from the methods is about, where their message does not already."""
    try:
        yield
    except InputError as exc:
        if str(path) in str(exc):
            raise
        raise type(exc)(f"{path}: {exc}") from None


def _umask() -> int:
    """The process umask, read without changing it where the system allows (Linux:
    /proc/self/status); elsewhere by setting and restoring it, which a thread creating a file at
    that moment could see."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def check_output_path(path: str | Path) -> Path:
    """Refuse, before any work, an output path that cannot become a file."""
    if str(path) == "":
        raise InputError("the output path is empty; give a file name")
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder; give the name of a file to write")
    folder = path.parent
    if not folder.exists():
        raise InputError(f"{path}: folder {folder} does not exist")
    if not folder.is_dir():
        raise InputError(f"{path}: {folder} is not a folder")
    return path


def check_not_overwriting(
    out: str | Path, option: str = "--out", **inputs: str | Path | None
) -> None:
    """Refuse an output path that is one of the command's input files (which it would replace)."""
    for name, inp in inputs.items():
        if inp is None:
            continue
        try:
            same = os.path.samefile(out, inp)
        except OSError:  # one of them does not exist (yet)
            same = False
        if same:
            raise InputError(
                f"{option} {out} is the input file --{name.replace('_', '-')} {inp}; "
                "write the result to another file so the input is kept"
            )


def _atomic_write(path: str | Path, write: Callable[[TextIO], object]) -> None:
    """Write through `write(fh)` to a temporary file beside `path`, then rename it into place."""
    path = check_output_path(path)
    folder = path.parent
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    try:
        # mkstemp makes the file private (0600); a result file gets the usual umask-based mode
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "w", newline="", encoding="utf-8") as fh:
            write(fh)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


class _RowLines:
    """Rows end in a plain newline, yet a cell holding a bare carriage return is still quoted.

    The csv writer quotes only cells holding characters of its line terminator, so it writes
    with "\r\n" and each row (one write call) has that ending replaced by "\n".
    """

    def __init__(self, fh: TextIO) -> None:
        self._fh = fh

    def write(self, row: str) -> int:
        return self._fh.write(row[:-2] + "\n")


def write_dataset(
    path: str | Path, columns: Mapping[str, Sequence[Any] | NDArray[np.float64]]
) -> None:
    """Write columns (numeric arrays or text lists) atomically."""
    names = list(columns)
    if not names:
        raise ValueError("nothing to write")
    n = len(columns[names[0]])
    for name in names:
        if len(columns[name]) != n:
            raise ValueError(f"column {name!r} has {len(columns[name])} values, expected {n}")

    def write(fh: TextIO) -> None:
        writer = csv.writer(_RowLines(fh), lineterminator="\r\n")
        writer.writerow(names)
        cols = [columns[name] for name in names]
        for i in range(n):
            writer.writerow([format_value(names[j], cols[j][i]) for j in range(len(names))])

    _atomic_write(path, write)


def write_text_atomic(path: str | Path, text: str) -> None:
    _atomic_write(path, lambda fh: fh.write(text))


# Units a tilt column is mistaken for, as (name, how many of them make a degree, how to convert).
_MISTAKEN_UNITS = (
    ("radians", math.pi / 180.0, "degrees = radians × 57.2958"),
    ("milliradians", 1000.0 * math.pi / 180.0, "degrees = milliradians × 0.0572958"),
    ("arc minutes", 60.0, "degrees = arc minutes / 60"),
    ("arc seconds", 3600.0, "degrees = arc seconds / 3600"),
    ("millidegrees", 1000.0, "degrees = millidegrees / 1000"),
)
# below this the stage moved too little to compare the sensors' spans with
STAGE_SPAN_TO_JUDGE_DEG = 0.5
# a sensor on the table reads the stage's tilt give or take its mounting, never more
TILT_MARGIN_DEG = 5.0


def check_stage_units(ds: Dataset, travel_deg: float) -> None:
    """Plausibility of the units of a stage run: every `_deg` column must be in degrees.

    The stage angles stay within the bench's travel, the sensors on the table read about what the
    stage tilts (their mounting adds a degree or two), and a sensor column whose readings span a
    fixed multiple of the stage's span (1/57.3: radians, 3600: arc seconds ...) is in another unit.
    A fit on such data fails far from the cause; this names the column.
    """
    cols = ds.numeric
    _check_stage_travel(ds, travel_deg)
    stage = [cols[column] for column in ("stage_x_deg", "stage_y_deg") if column in cols]
    if not stage:
        return
    stage_span = max(float(np.ptp(angles)) for angles in stage)
    _check_sensor_tilts(ds, travel_deg, stage_span)
    # A sensor's two axes together span about what the stages do (a run may move one stage only, and
    # a sensor may sit turned on the table, so an axis is not compared with one stage alone).
    for sensor in ("ref", "meas"):
        _check_sensor_span(ds, sensor, stage_span)


def _check_stage_travel(ds: Dataset, travel_deg: float) -> None:
    """The stage angles within the bench's travel (degrees, not another unit)."""
    cols = ds.numeric
    for col in ("stage_x_deg", "stage_y_deg"):
        if col in cols and (beyond := np.flatnonzero(np.abs(cols[col]) > travel_deg + 1e-9)).size:
            i = int(beyond[0])
            raise InputError(
                f"{ds.where(i + 1, col)}: {ds.text[col][i]} is beyond the stage's travel of "
                f"±{travel_deg:g} deg; the column must hold the stage angle in degrees"
            )


def _check_sensor_tilts(ds: Dataset, travel_deg: float, stage_span: float) -> None:
    """No sensor reading more tilt than the table can show: the travel and a mounting's margin."""
    cols = ds.numeric
    limit = travel_deg + TILT_MARGIN_DEG
    for col in ("ref_x_deg", "ref_y_deg", "meas_x_deg", "meas_y_deg"):
        if col in cols and (beyond := np.flatnonzero(np.abs(cols[col]) > limit)).size:
            i = int(beyond[0])
            raise InputError(
                f"{ds.where(i + 1, col)}: {ds.text[col][i]} is more tilt than the table can show "
                f"(the stage travels ±{travel_deg:g} deg): the column must hold the sensor's "
                "reading in degrees" + _unit_hint(float(np.ptp(cols[col])), stage_span)
            )


def _check_sensor_span(ds: Dataset, sensor: str, stage_span: float) -> None:
    """A sensor's wider axis spans within a factor of two of the stages' span; otherwise the
    sensor's column or the stage's is in another unit, named with the unit it looks like."""
    cols = ds.numeric
    pair = [column for column in (f"{sensor}_x_deg", f"{sensor}_y_deg") if column in cols]
    if not pair:
        return
    col = max(pair, key=lambda c: float(np.ptp(cols[c])))
    span = float(np.ptp(cols[col]))
    if (
        max(span, stage_span) < STAGE_SPAN_TO_JUDGE_DEG
        or 0.5 <= span / max(stage_span, 1e-12) <= 2.0
    ):
        return
    # the sensor reads far less than the stage tilts: it is not in degrees
    if span < stage_span:
        raise InputError(
            f"{ds.source}: column {col}: its readings span {span:.4g} while the stage spans "
            f"{stage_span:.4g} deg (a sensor on the table reads about what the stage tilts): "
            "the column must hold degrees" + _unit_hint(span, stage_span)
        )
    stage_col = max(
        (column for column in ("stage_x_deg", "stage_y_deg") if column in cols),
        key=lambda c: float(np.ptp(cols[c])),
    )
    raise InputError(
        f"{ds.source}: column {stage_col}: the stage spans {stage_span:.4g} while {col} "
        f"reads a tilt spanning {span:.4g} deg (a sensor on the table reads about what the "
        "stage tilts): the stage angles must be in degrees" + _unit_hint(stage_span, span)
    )


def _unit_hint(span: float, stage_span_deg: float) -> str:
    """`; it looks like radians (degrees = ...)` when the spans' ratio is that of a known unit."""
    if stage_span_deg < STAGE_SPAN_TO_JUDGE_DEG or span <= 0:
        return ""
    ratio = span / stage_span_deg
    for name, per_degree, convert in _MISTAKEN_UNITS:
        if abs(ratio / per_degree - 1.0) < 0.2:
            return f"; it looks like {name} ({convert})"
    return ""
