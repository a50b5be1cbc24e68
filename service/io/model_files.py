"""Reading and writing MODEL.json files (the I/O edge of service.calibration.model)."""

from __future__ import annotations

import json
from pathlib import Path

from service.calibration.model import CalibrationModel
from service.errors import InputError
from service.io.datasets import write_text_atomic


def read_model(path: str | Path) -> CalibrationModel:
    try:
        # a BOM from a Windows editor is harmless
        data = json.loads(Path(path).read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        raise InputError(f"{path}: no such model file") from None
    except json.JSONDecodeError as exc:
        raise InputError(
            f"{path}: not valid JSON: line {exc.lineno} column {exc.colno}: {exc.msg}"
        ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read: {exc}") from None
    except RecursionError:
        raise InputError(f"{path}: not a model: JSON nested too deeply") from None
    return CalibrationModel.from_json_dict(data, source=str(path))


def write_model(path: str | Path, model: CalibrationModel) -> None:
    write_text_atomic(path, json.dumps(model.to_json_dict(), indent=2, allow_nan=False) + "\n")
