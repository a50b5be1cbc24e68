"""Stage calibration methods (kind `stage`): homography (seed 000), coupling (its ref. [9]),
axis-transform (its ref. [10]) and kinematic (the full chain of docs/models.md §2), one module each
on the shared base class `StageMethod`.

Every method levels (wanted table tilt -> stage commands) and corrects (measurement-sensor
reading -> table tilt). The readings of refs. [9] and [10] are written out in
docs/calibration-stage.md and in each model's notes.
"""

from service.calibration.methods.stage.axis_transform import AXIS_TRANSFORM, AxisTransformMethod
from service.calibration.methods.stage.base import (
    StageMethod,
    bench_state,
    stage_commands,
    stage_hardware,
)
from service.calibration.methods.stage.common import LEVEL_OUTPUTS
from service.calibration.methods.stage.coupling import COUPLING, CouplingMethod
from service.calibration.methods.stage.homography import HOMOGRAPHY, HomographyMethod
from service.calibration.methods.stage.kinematic import KINEMATIC, KinematicMethod

__all__ = [
    "AXIS_TRANSFORM",
    "COUPLING",
    "HOMOGRAPHY",
    "KINEMATIC",
    "LEVEL_OUTPUTS",
    "AxisTransformMethod",
    "CouplingMethod",
    "HomographyMethod",
    "KinematicMethod",
    "StageMethod",
    "stage_hardware",
    "bench_state",
    "stage_commands",
]
