"""Dataset column names, the one place they are written (the offline contract, docs/ and the README).

Physics returns readings keyed by these names, the simulator writes them in the `*_DATASET`
order, the methods read them, and `read_dataset` checks their values.
"""

from __future__ import annotations

# stage: two stacked swing stages, a reference and a measurement sensor on the table
POINT = "point"
STAGE = ("stage_x_deg", "stage_y_deg")  # commanded angles, as the controller executes them (whole pulses)
TARGET = ("target_x_deg", "target_y_deg")  # wanted table tilt (levelling input)
DIRECTION = ("dir_x", "dir_y")  # sign of the last move of each stage (backlash)
REF = ("ref_x_deg", "ref_y_deg")
MEAS = ("meas_x_deg", "meas_y_deg")
TEMP = "temp_c"
TIME = "t_s"
TILT_OUTPUTS = ("tilt_x_deg", "tilt_y_deg", "u_tilt_x_deg", "u_tilt_y_deg")  # what `correct` adds
# Coverage factors of u_tilt_x_deg / u_tilt_y_deg (95 %, effective degrees of freedom): returned by a
# stage method's `correct` beside TILT_OUTPUTS for the daemon, not written to dataset files.
K_OUTPUTS = ("k_tilt_x", "k_tilt_y")
STAGE_DATASET = (POINT, *STAGE, *DIRECTION, *REF, *MEAS, TEMP, TIME)

# rotation: a triaxial module on a rotary table
ROTATION_DATASET = (POINT, "theta_ref_deg", "sx", "sy", "sz")

# scale: an analog sensor read through an ADC against a reference angle
SCALE_REFERENCE = ("ref_arcsec", "ref_deg")  # either one
SCALE_DATASET = (POINT, "ref_arcsec", "reading")

# turntable: an inclinometer read at two positions half a turn apart, against a star reference
TURNTABLE_READINGS = ("n1_a", "n2_a", "n1_b", "n2_b")
TURNTABLE_DATASET = ("cycle", "azimuth_deg", *TURNTABLE_READINGS, "ref_north_arcsec", "ref_east_arcsec")

INTEGER_COLUMNS = frozenset({POINT, "cycle", *DIRECTION, "reading"})  # written without a decimal point
