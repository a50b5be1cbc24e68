"""Calibration jobs run by the daemon on its benches, through the same calibration code as the
CLI."""
