"""Calibration methods (pure numpy/scipy, no I/O): fit models to datasets and apply them."""

from service.calibration.model import CalibrationModel, Parameter  # noqa: F401
from service.calibration.registry import FitOptions, get_method, methods_for  # noqa: F401
