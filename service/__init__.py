"""tiltlab: calibration, measurement and control of tilt with biaxial inclinometers."""

__version__ = "0.1.0"
