"""Dataset column names, the one place they are written (the offline contract, docs/ and the
README).

Physics returns readings keyed by these names, the simulator writes them in the `*_DATASET`
order, the methods read them, and `read_dataset` checks their values.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # numpy is imported where the columns are computed, not with their names
    import numpy as np
    from numpy.typing import NDArray

# stage: two stacked swing stages, a reference and a measurement sensor on the table
POINT = "point"
# commanded angles, as the controller executes them (whole pulses)
STAGE = ("stage_x_deg", "stage_y_deg")
TARGET = ("target_x_deg", "target_y_deg")  # wanted table tilt (levelling input)
DIRECTION = ("dir_x", "dir_y")  # sign of the last move of each stage (backlash)
REF = ("ref_x_deg", "ref_y_deg")
MEAS = ("meas_x_deg", "meas_y_deg")
TEMP = "temp_c"
TIME = "t_s"
TILT_OUTPUTS = ("tilt_x_deg", "tilt_y_deg", "u_tilt_x_deg", "u_tilt_y_deg")  # what `correct` adds
# Coverage factors of u_tilt_x_deg / u_tilt_y_deg (95 %, effective degrees of freedom): returned by
# a stage method's `correct` beside TILT_OUTPUTS for the daemon, not written to dataset files.
K_OUTPUTS = ("k_tilt_x", "k_tilt_y")
STAGE_DATASET = (POINT, *STAGE, *DIRECTION, *REF, *MEAS, TEMP, TIME)

# rotation: a triaxial module on a rotary table
ROTATION_DATASET = (POINT, "theta_ref_deg", "sx", "sy", "sz")

# scale: an analog sensor read through an ADC against a reference angle
SCALE_REFERENCE = ("ref_arcsec", "ref_deg")  # either one
SCALE_DATASET = (POINT, "ref_arcsec", "reading")

# turntable: an inclinometer read at two positions half a turn apart, against a star reference
TURNTABLE_READINGS = ("n1_a", "n2_a", "n1_b", "n2_b")
TURNTABLE_DATASET = (
    "cycle",
    "azimuth_deg",
    *TURNTABLE_READINGS,
    "ref_north_arcsec",
    "ref_east_arcsec",
)

# Uncertainty columns of `correct` (docs/datasets.md). A method returns, per corrected quantity q
# (e.g. tilt_x_deg), its expanded uncertainty as `u_<q>` and the coverage factor as `k_<q without
# its unit>`; the files name them so that nobody can read one for the other (GUM: u is a standard
# uncertainty, U = k·u the expanded one).
COVERAGE_PROBABILITY = "coverage_probability"
# files before this release: `u_<q>` held the expanded uncertainty
DEPRECATED_UNCERTAINTY_PREFIX = "u_"


def _bare(q: str) -> str:
    for unit in ("_deg", "_arcsec"):
        if q.endswith(unit):
            return q[: -len(unit)]
    return q


def uncertainty_names(q: str) -> dict[str, str]:
    """The columns `correct` writes for quantity q: expanded and standard uncertainty, coverage
    factor."""
    return {
        "expanded": f"expanded_uncertainty_{q}",
        "standard": f"standard_uncertainty_{q}",
        "coverage_factor": f"coverage_factor_{_bare(q)}",
    }


def uncertainty_columns(
    result: Mapping[str, NDArray[np.float64]],
    quantities: tuple[str, ...],
    coverage: float,
    deprecated: bool = False,
) -> dict[str, NDArray[np.float64]]:
    """A method's corrected values as `correct` writes them: each value, then its uncertainty
    columns, named."""
    import numpy as np

    out: dict[str, NDArray[np.float64]] = {}
    any_u = False
    for quantity in quantities:
        out[quantity] = result[quantity]
        expanded = result.get(f"u_{quantity}")
        if expanded is None:
            continue
        any_u = True
        k = np.asarray(result[f"k_{_bare(quantity)}"], dtype=float)
        names = uncertainty_names(quantity)
        out[names["expanded"]] = expanded
        out[names["standard"]] = np.asarray(expanded, dtype=float) / k
        out[names["coverage_factor"]] = np.broadcast_to(k, np.shape(expanded))
        if deprecated:
            out[f"u_{quantity}"] = expanded
    if any_u:
        out[COVERAGE_PROBABILITY] = np.full(np.shape(result[quantities[0]]), coverage)
    return out


# written without a decimal point
INTEGER_COLUMNS = frozenset({POINT, "cycle", *DIRECTION, "reading"})
