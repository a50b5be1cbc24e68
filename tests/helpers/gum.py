"""Getting the standard uncertainty u_c back from a method's expanded output.

With the degrees of freedom unknown (infinite) the coverage factor is the normal quantile for
95 %, the same for every point, so U / Z95 is u_c exactly; the tests that compare u_c with Monte
Carlo use that, and the coverage-factor law itself is tested in test_uncertainty.py.
"""

import copy

import numpy as np

from service.calibration.uncertainty import coverage_factor

Z95 = float(coverage_factor(np.inf))
DOF_KEYS = ("dof", "meas_dof", "reading_sigma_dof", "meas_reading_dof")


def without_dof(model):
    m = copy.deepcopy(model)
    for doc in (m.state, m.fit):
        for key in DOF_KEYS:
            if key in doc:
                doc[key] = None
    return m
