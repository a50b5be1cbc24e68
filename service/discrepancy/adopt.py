"""Adopting a diagnosis: the kinematic calibration refitted on the same points with the named effects switched on.

The last step of the workflow, shared by the daemon (`POST /diagnoses/{id}/adopt`) and the command line
(`tiltlab discrepancy --adopt MODEL.json`): the model it writes states which effects were added and from which
diagnosis, and `tiltlab correct`, `tiltlab level` and the daemon's levelling use them like any other parameter.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.calibration.methods.stage.chain import EXTRA_EFFECTS, IN_CHAIN
from service.calibration.model import CalibrationModel
from service.calibration.registry import FitOptions, get_method
from service.errors import InputError
from service.physics.stage import StageBench


class NothingToAdopt(InputError):
    """The diagnosis named no effect the calibration does not already have."""


def effects_to_add(named: Sequence[str], sensor: str) -> list[str]:
    """The named effects the calibration adds; NothingToAdopt when none is left, InputError for one it cannot add."""
    extra = [e for e in named if e not in IN_CHAIN]
    if not extra:
        raise NothingToAdopt("the diagnosis named no effect beyond what the kinematic calibration already has"
                             + (f" ({', '.join(named)})" if named else "") + ": there is nothing to adopt")
    cannot = [e for e in extra if e not in EXTRA_EFFECTS]
    if cannot:
        raise InputError(f"{', '.join(cannot)} cannot be added to the kinematic calibration (it takes "
                         f"{', '.join(EXTRA_EFFECTS)})")
    if sensor != "ref" and any(e != "periodic_error" for e in extra):
        raise InputError(f"the diagnosis explained the measurement sensor's readings; {', '.join(extra)} of that "
                         "sensor cannot be added to the calibration, which fits the chain to the reference sensor: "
                         "diagnose with sensor 'ref'")
    return extra


def adopted_model(columns: Mapping[str, NDArray[np.float64]], named: Sequence[str], sensor: str,
                  bench: StageBench | Mapping[str, Any], bench_source: str,
                  diagnosis: Mapping[str, Any]) -> CalibrationModel:
    """The kinematic calibration of `columns` with the diagnosis' named effects added; `diagnosis` says where they
    came from (kept in the model's state with the effects)."""
    effects = effects_to_add(named, sensor)
    hw = bench if isinstance(bench, StageBench) else StageBench(**bench)
    model = get_method("stage", "kinematic").fit(
        columns, FitOptions(extra={"bench": hw, "bench_source": bench_source, "effects": effects}))
    model.state["added_effects"] = effects
    model.state["diagnosis"] = dict(diagnosis)
    model.notes.append(f"adopted from {diagnosis.get('what', 'a diagnosis')}: added {', '.join(effects)}")
    return model
