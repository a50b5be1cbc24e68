"""Pieces every stage method shares: seed 000's printed eq. (10) compensation against the exact
inverse (the relation itself is service.physics.stage's), the sensor geometry in
the reference (table-tilt) frame, mirrored-axis detection, column checks and a vectorised
2-D Newton solver.

Frames: the *truth frame* is the reference sensor's orthogonal axes (docs/models.md §2: table tilt
is what the reference reads without noise). An inclinometer reading depends only on the up
vector n expressed in the frame of the body carrying it (docs/models.md §1: reading = asin(-a·n)),
so a table tilt (X, Y) is the same thing as n = (-sin X, -sin Y, +sqrt(1 - sin²X - sin²Y)).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.calibration.differences import fd_step
from service.calibration.model import CalibrationModel
from service.calibration.registry import FitExtras
from service.calibration.uncertainty import Propagated, welch_satterthwaite
from service.errors import DegenerateDataError, InputError
from service.io import columns as columns_
from service.physics.stage import offaxis_error_deg, offaxis_inverse_deg, offaxis_reading_deg

STAGE_COLUMNS, REF_COLUMNS, MEAS_COLUMNS = columns_.STAGE, columns_.REF, columns_.MEAS
TILT_OUTPUTS = columns_.TILT_OUTPUTS
LEVEL_OUTPUTS = columns_.STAGE  # what `level` writes: the stage commands
GRID_12_DEG = np.arange(-12.0, 12.0 + 1e-9, 3.0)  # seed 000's validation grid (§4.4)
ROBUST_LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")


# --- seed 000's printed compensation against the exact inverse of eq. (9) (service.physics.stage)
# -------------
def offaxis_paper_forward_deg(
    x_decoupled_deg: ArrayLike, stage_y_deg: ArrayLike
) -> NDArray[np.float64]:
    """Seed 000's compensation as printed: add eq. (10)'s error, evaluated at the wanted angle, to
    x."""
    return np.asarray(x_decoupled_deg, dtype=float) + offaxis_error_deg(
        x_decoupled_deg, stage_y_deg
    )


def offaxis_forward_vs_exact_deg(grid_deg: NDArray[np.float64] = GRID_12_DEG) -> dict[str, float]:
    """How far the paper's forward form lands from the exact inverse over a square grid of (x',
    y)."""
    grid_x, grid_y = np.meshgrid(grid_deg, grid_deg)
    diff = offaxis_paper_forward_deg(grid_x, grid_y) - offaxis_inverse_deg(grid_x, grid_y)
    i = int(np.argmax(np.abs(diff)))
    # The command difference is also (to first order) the x tilt error it causes: dX/dx = cos y·cos
    # x/cos X ≈ 1.
    reached = offaxis_reading_deg(offaxis_paper_forward_deg(grid_x, grid_y), grid_y) - grid_x
    return {
        "grid_min_deg": float(grid_deg.min()),
        "grid_max_deg": float(grid_deg.max()),
        "max_abs_command_difference_deg": float(np.abs(diff).max()),
        "rms_command_difference_deg": float(np.sqrt(np.mean(diff**2))),
        "at_x_deg": float(grid_x.ravel()[i]),
        "at_y_deg": float(grid_y.ravel()[i]),
        "max_abs_x_tilt_error_deg": float(np.abs(reached).max()),
    }


# --- tilt <-> up vector in the truth frame --------------------------------------------------
def up_from_tilt(tilt_x_deg: ArrayLike, tilt_y_deg: ArrayLike) -> NDArray[np.float64]:
    """Up vector (N, 3) in the truth frame for table tilts (X, Y)."""
    sx, sy = np.sin(np.radians(tilt_x_deg)), np.sin(np.radians(tilt_y_deg))
    nz = np.sqrt(np.clip(1.0 - sx**2 - sy**2, 0.0, None))
    up: NDArray[np.float64] = np.stack([-sx, -sy, nz], axis=-1)
    return up


def plane_tilt_matrix(tilt_x_deg: float, tilt_y_deg: float) -> NDArray[np.float64]:
    """Same composition as service.physics.rotations.plane_tilt: Rx(-tilt_y)·Ry(tilt_x)."""
    from service.physics.rotations import plane_tilt

    return plane_tilt(np.radians(tilt_x_deg), np.radians(tilt_y_deg))


# --- measurement sensor in the truth frame (kinematic) --------------------------------------
MEAS_PARAMS = (  # (name in MODEL.json, unit, typical magnitude for the solver)
    ("zero_offset.meas_x_deg", "deg", 0.1),
    ("zero_offset.meas_y_deg", "deg", 0.1),
    ("scale_factor.meas_x", "1", 1e-3),
    ("scale_factor.meas_y", "1", 1e-3),
    ("sensor_yaw.meas_deg", "deg", 0.1),
    ("non_orthogonality.meas_deg", "deg", 0.1),
    ("mounting_tilt.meas_x_deg", "deg", 0.1),
    ("mounting_tilt.meas_y_deg", "deg", 0.1),
)
MEAS_NAMES = tuple(meas_param[0] for meas_param in MEAS_PARAMS)


def meas_axes(p: NDArray[np.float64]) -> NDArray[np.float64]:
    """Sensing axes (2, 3) of the measurement sensor in the truth frame: seat tilt · yaw · (x, y at
    90° + ν)."""
    yaw, nu = np.radians(p[4]), np.radians(p[5])
    seat = plane_tilt_matrix(p[6], p[7])
    cos_yaw, sin_yaw = np.cos(yaw), np.sin(yaw)
    rz = np.array([[cos_yaw, -sin_yaw, 0.0], [sin_yaw, cos_yaw, 0.0], [0.0, 0.0, 1.0]])
    base = np.array([[1.0, 0.0, 0.0], [-np.sin(nu), np.cos(nu), 0.0]])
    axes: NDArray[np.float64] = (seat @ rz @ base.T).T
    return axes


def meas_forward(
    p: NDArray[np.float64], sign: NDArray[np.float64], tilt_x_deg: ArrayLike, tilt_y_deg: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Noise-free measurement-sensor readings at table tilts (X, Y) for parameters p (MEAS_PARAMS
    order)."""
    n = up_from_tilt(tilt_x_deg, tilt_y_deg)
    m = meas_axes(p)
    geo = np.degrees(np.arcsin(np.clip(-(n @ m.T), -1.0, 1.0)))  # (N, 2)
    read_a = p[0] + (1.0 + p[2]) * sign[0] * geo[..., 0]
    read_b = p[1] + (1.0 + p[3]) * sign[1] * geo[..., 1]
    return read_a, read_b


def _frame(P: NDArray[np.float64], full: bool = False) -> tuple[NDArray[np.float64], ...]:
    """meas_axes multiplied out for K parameter sets P (K, 8): every entry a (K, 1) column.

    Same composition (seat Rx(-tilt_y)·Ry(tilt_x) · yaw Rz(yaw) · base): Rz(yaw)·base puts the x
    axis at (c, s, 0) and the y axis at (-(c·sin ν + s·cos ν), c·cos ν - s·sin ν, 0); the seat is
    [[cx, 0, sx], [-sx·sy, cy, cx·sy], [-sx·cy, -sy, cx·cy]]. Returns the first two entries of
    each axis (x0, x1, y0, y1), then sin ν, cos ν and the seat's (sx, cx·sy, cx·cy), its third
    column; `full` adds the third entries (x2, y2).
    """
    ang = (np.pi / 180.0) * P[:, 4:8]  # yaw, non-orthogonality, seat x, seat y
    cos, sin = np.cos(ang), np.sin(ang)
    cos_yaw, cn, cx, cy = cos[:, 0:1], cos[:, 1:2], cos[:, 2:3], cos[:, 3:4]
    sin_yaw, sn, sx, sy = sin[:, 0:1], sin[:, 1:2], sin[:, 2:3], sin[:, 3:4]
    u0, u1 = -(cos_yaw * sn + sin_yaw * cn), cos_yaw * cn - sin_yaw * sn  # y axis after the yaw
    sxsy = sx * sy
    out: tuple[NDArray[np.float64], ...] = (
        cx * cos_yaw,
        cy * sin_yaw - sxsy * cos_yaw,
        cx * u0,
        cy * u1 - sxsy * u0,
        sn,
        cn,
        sx,
        cx * sy,
        cx * cy,
    )
    if full:
        sxcy = sx * cy
        out += (-(sxcy * cos_yaw + sy * sin_yaw), -(sxcy * u0 + sy * u1))
    return out


def meas_axes_batch(P: ArrayLike) -> NDArray[np.float64]:
    """meas_axes for K parameter sets at once: P (K, 8) in MEAS_PARAMS order gives axes (K, 2,
    3)."""
    param_sets = np.asarray(P, dtype=float)
    x0, x1, y0, y1, *_, x2, y2 = _frame(param_sets, full=True)
    axes: NDArray[np.float64] = np.concatenate([x0, x1, x2, y0, y1, y2], axis=1).reshape(
        param_sets.shape[0], 2, 3
    )
    return axes


def _solve_batch(
    P: NDArray[np.float64], sign: NDArray[np.float64], R: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Table tilt (2, K, N) in degrees from readings R (2, K, N) (x then y), row k read through P[k]
    (K, 8).

    Each axis reading fixes m·n (a plane); two planes and |n| = 1 leave two points, and the one
    with the table's normal up is the answer. Both axes are rotations of (1, 0, 0) and
    (-sin ν, cos ν, 0), so the Gram matrix m mᵀ is [[1, -sin ν], [-sin ν, 1]] (inverse
    [[1, sin ν], [sin ν, 1]] / cos²ν) and m_x × m_y = cos ν · (the seat's third column): both in
    closed form per parameter set, so one call serves every case of the uncertainty evaluation.
    """
    x0, x1, y0, y1, sn, cn, w0, w1, w2 = _frame(P)  # (w0, w1, w2): the seat's third column
    inv = 1.0 / (cn * cn)  # 1 / det(m mᵀ)
    # the unit normal to both axes is ± the seat's third column: the one with the table's normal up
    up = np.copysign(1.0, w2)
    wx, wy = up * w0, up * w1
    gain = (np.asarray(sign, dtype=float) * (np.pi / 180.0))[:, None, None] / (
        1.0 + P[:, 2:4].T[:, :, None]
    )
    rhs = -np.sin(gain * (R - P[:, 0:2].T[:, :, None]))  # (m_x · n, m_y · n)
    ra, rb = rhs[0], rhs[1]
    c1 = inv * (ra + sn * rb)  # n0 = c1 m_x + c2 m_y: the minimum-norm point on both planes
    c2 = inv * (rb + sn * ra)
    t = np.sqrt(np.maximum(1.0 - (c1 * ra + c2 * rb), 0.0))  # |n0|² = rhsᵀ G⁻¹ rhs
    n = np.empty(R.shape)
    np.add(c1 * x0 + c2 * y0, t * wx, out=n[0])
    np.add(c1 * x1 + c2 * y1, t * wy, out=n[1])
    # the reading is asin(-a·n); in place, so many readings need no further arrays
    np.negative(n, out=n)
    np.maximum(n, -1.0, out=n)
    np.minimum(n, 1.0, out=n)
    tilt: NDArray[np.float64] = np.degrees(np.arcsin(n, out=n), out=n)
    return tilt


def meas_inverse_batch(
    P: ArrayLike, sign: NDArray[np.float64], meas_x_deg: ArrayLike, meas_y_deg: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """meas_inverse for K parameter sets at once: P (K, 8), readings (K, N) with row k read through
    P[k]."""
    param_sets = np.asarray(P, dtype=float)
    readings = np.stack(
        np.broadcast_arrays(
            np.asarray(meas_x_deg, dtype=float), np.asarray(meas_y_deg, dtype=float)
        )
    )
    tilt = _solve_batch(param_sets, sign, readings.reshape(2, param_sets.shape[0], -1)).reshape(
        readings.shape
    )
    return tilt[0], tilt[1]


def meas_inverse(
    p: NDArray[np.float64], sign: NDArray[np.float64], meas_x_deg: ArrayLike, meas_y_deg: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Table tilt from measurement readings, in closed form (exact, vectorised, no iteration; see
    _solve_batch)."""
    read_a, read_b = np.broadcast_arrays(
        np.asarray(meas_x_deg, dtype=float), np.asarray(meas_y_deg, dtype=float)
    )
    tilt = _solve_batch(
        np.asarray(p, dtype=float)[None], sign, np.stack([read_a, read_b]).reshape(2, 1, -1)
    ).reshape((2,) + read_a.shape)
    return tilt[0], tilt[1]


# up to this many (case, reading) pairs, every case is solved in one evaluation
_STACKED_READINGS = 4096
# sign of the step of (a, b) in each case
_READING_STEPS = np.zeros((2, 5 + 2 * (len(MEAS_PARAMS) - 4)))
_READING_STEPS[0, 1:3] = _READING_STEPS[1, 3:5] = (1.0, -1.0)


def meas_inverse_gum(
    p: NDArray[np.float64],
    cov: NDArray[np.float64] | None,
    sign: NDArray[np.float64],
    meas_x_deg: ArrayLike,
    meas_y_deg: ArrayLike,
    sigma_deg: float,
    dof: float = np.inf,
    noise_dof: float | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], Propagated, Propagated]:
    """meas_inverse with the standard uncertainty and effective degrees of freedom of each output.

    Same law as service.calibration.uncertainty.propagate_gum (central differences; each reading
    and the parameters' covariance one component, all from one fit with `dof` degrees of
    freedom), but the zero and scale sensitivities follow from the reading's own (reading a
    enters only as (a - zero)/(1 + scale)), so 13 evaluations replace 21: this is what keeps
    correct above 10^5 readings per second. The cases (central value, each reading stepped up and
    down, each parameter with a nonzero covariance row stepped) are one batched evaluation for a
    few readings, where call overhead rather than arithmetic is the cost (one reading is the
    daemon's case), and two cases at a time for many, which keeps the working arrays near the
    input's size.
    """
    params = np.asarray(p, dtype=float)
    read_a = np.asarray(meas_x_deg, dtype=float)
    read_b = np.asarray(meas_y_deg, dtype=float)
    if read_a.shape != read_b.shape:
        read_a, read_b = np.broadcast_arrays(read_a, read_b)
    shape, n = read_a.shape, read_a.size
    ab = np.concatenate([read_a.reshape(1, -1), read_b.reshape(1, -1)])  # (a, b) x reading
    # rows of held parameters are zero
    nonzero = np.asarray(cov.any(axis=1) if cov is not None else np.zeros(params.size, dtype=bool))
    has_cov = bool(nonzero.any())
    # parameters stepped: zero and scale follow from the readings
    stepped = nonzero[4:].nonzero()[0] + 4
    m = stepped.size
    steps = fd_step(np.concatenate([ab.reshape(-1), params[stepped]]), 1.0)
    # steps of the readings (a, b) and of the stepped parameters
    hab, hp = steps[: 2 * n].reshape(2, n), steps[2 * n :]
    n_cases = 5 + 2 * m
    case_params = np.repeat(params[None], n_cases, axis=0)
    flat = case_params.reshape(-1)
    # case 5 + 2j steps parameter stepped[j] up, case 6 + 2j down
    at = np.arange(5, n_cases, 2) * params.size + stepped
    flat[at] += hp
    flat[at + params.size] -= hp
    if n_cases * n <= _STACKED_READINGS:
        # a ± ha in cases 1, 2, b ± hb in 3, 4
        case_readings = ab[:, None] + _READING_STEPS[:, :n_cases, None] * hab[:, None]
        case_tilts = _solve_batch(case_params, sign, case_readings)  # (X, Y) x case x reading
        Z0 = case_tilts[:, 0]
        d_reading = (case_tilts[:, 1:5:2] - case_tilts[:, 2:5:2]) / (
            2 * hab
        )  # (X, Y) x (d/da, d/db) x reading
        # (X, Y) x d/d(stepped parameter) x reading
        d_params = (case_tilts[:, 5::2] - case_tilts[:, 6::2]) / (2 * hp)[:, None]
    else:  # the same differences, holding two cases at a time

        def case(c: int) -> NDArray[np.float64]:
            case_readings = ab[:, None]
            if c in (1, 2, 3, 4):  # a + ha, a - ha, b + hb, b - hb
                axis, case_readings = (c - 1) // 2, case_readings.copy()
                case_readings[axis, 0] = ab[axis] + hab[axis] if c % 2 else ab[axis] - hab[axis]
            return _solve_batch(case_params[c : c + 1], sign, case_readings)[:, 0]

        Z0, d_reading, d_params = case(0), np.empty((2, 2, n)), np.empty((2, m, n))
        for j in range(2):
            d_reading[:, j] = (case(1 + 2 * j) - case(2 + 2 * j)) / (2 * hab[j])
        for j in range(m):
            d_params[:, j] = (case(5 + 2 * j) - case(6 + 2 * j)) / (2 * hp[j])
    var_reading = (sigma_deg * d_reading) ** 2
    nd = dof if noise_dof is None else noise_dof  # the reading noise may rest on its own estimate
    parts = [(var_reading[:, 0], nd), (var_reading[:, 1], nd)]
    if cov is not None and has_cov:
        k = -(ab - params[0:2, None]) / (
            1.0 + params[2:4, None]
        )  # d/dscale = d/da·k, d/dzero = -d/da
        # parameters with a zero covariance row add nothing
        used = np.concatenate([np.arange(4), stepped])
        jacobian = np.concatenate([-d_reading, d_reading * k, d_params], axis=1)
        # no BLAS: steady under load
        parts.append(
            (np.einsum("kin,ij,kjn->kn", jacobian, cov[used[:, None], used], jacobian), dof)
        )
    u_c = np.sqrt(sum(var for var, _ in parts)).reshape((2,) + shape)
    nu = welch_satterthwaite(parts).reshape((2,) + shape)
    Z0 = Z0.reshape((2,) + shape)
    return Z0[0], Z0[1], Propagated(u_c[0], nu[0]), Propagated(u_c[1], nu[1])


# --- mirrored axes ---------------------------------------------------------------------------
def detect_mirror(
    sensor_x: ArrayLike,
    sensor_y: ArrayLike,
    ref_x: ArrayLike,
    ref_y: ArrayLike,
    what: str = "measurement sensor",
) -> NDArray[np.float64]:
    """Sign of each sensor axis against the matching reference axis: -1 for an axis mounted
    mirrored.

    An upside-down sensor (docs/models.md §2) mirrors one axis; the slope of that axis against the
    reference is then near -1 instead of +1, which no small mounting error can produce.
    """
    out = []
    for sensor, ref, ax in ((sensor_x, ref_x, "x"), (sensor_y, ref_y, "y")):
        sensor_deg = np.asarray(sensor, dtype=float)
        ref_deg = np.asarray(ref, dtype=float)
        rc = ref_deg - ref_deg.mean()
        if float(rc @ rc) <= 1e-12:
            raise DegenerateDataError(
                f"the {what}'s {ax} axis cannot be related to the reference: ref_{ax}_deg does "
                f"not change over the points (move the {'upper' if ax == 'x' else 'lower'} stage)"
            )
        slope = float(rc @ (sensor_deg - sensor_deg.mean()) / (rc @ rc))
        if abs(abs(slope) - 1.0) > 0.5:
            raise DegenerateDataError(
                f"the {what}'s {ax} reading does not follow ref_{ax}_deg (slope {slope:.3g}); "
                f"its axes may be swapped or the columns mislabelled"
            )
        out.append(1.0 if slope > 0 else -1.0)
    return np.array(out)


def mirror_note(sign: ArrayLike) -> str | None:
    sign = np.asarray(sign)
    sx, sy = float(sign[0]), float(sign[1])
    if sx > 0 and sy > 0:
        return None
    if sx < 0 and sy < 0:
        return (
            "measurement sensor turned 180 deg about its normal: both axes read against the "
            "reference"
        )
    ax, about = ("y", "x") if sy < 0 else ("x", "y")
    return (
        f"measurement sensor mounted upside down (turned about its {about} axis): its {ax} axis is "
        f"mirrored against the reference; modelled as a sign on that axis"
    )


def sign_from_options(
    options_extra: FitExtras, detected: NDArray[np.float64]
) -> tuple[NDArray[np.float64], str]:
    """The lab may state the mounting ('none', 'x', 'y': the axis it was turned about); otherwise
    detect it."""
    flip = options_extra.get("meas_flip", "auto")
    if flip == "auto":
        return detected, "detected from the data"
    table = {"none": (1.0, 1.0), "x": (1.0, -1.0), "y": (-1.0, 1.0)}
    if flip not in table:
        raise InputError(f"option meas_flip: {flip!r} is not one of auto, none, x, y")
    sign = np.array(table[flip])
    if not np.array_equal(sign, detected):
        raise DegenerateDataError(
            f"option meas_flip={flip!r} contradicts the data: the measurement readings "
            f"run with signs {detected.tolist()} against the reference"
        )
    return sign, "as stated by the lab"


# --- input checks ----------------------------------------------------------------------------
def columns(
    data: Mapping[str, NDArray[np.float64]], names: Iterable[str]
) -> list[NDArray[np.float64]]:
    names = list(names)
    missing = [n for n in names if n not in data]
    if missing:
        raise InputError(f"missing required column {missing[0]!r}")
    return [np.asarray(data[n], dtype=float) for n in names]


def has_meas(data: Mapping[str, NDArray[np.float64]]) -> bool:
    return all(meas_column in data for meas_column in MEAS_COLUMNS)


def require_spread(
    stage_x: NDArray[np.float64], stage_y: NDArray[np.float64], min_points: int, what: str
) -> None:
    """Both stages must move, at enough distinct points, for any stage model to be determined."""
    pts = np.unique(np.round(np.column_stack([stage_x, stage_y]), 6), axis=0)
    if len(pts) < min_points:
        raise DegenerateDataError(
            f"{what} needs at least {min_points} distinct stage points, got {len(pts)}"
        )
    for name, angles, stage in (
        ("stage_x_deg", stage_x, "upper"),
        ("stage_y_deg", stage_y, "lower"),
    ):
        if np.unique(np.round(angles, 6)).size < 2:
            raise DegenerateDataError(
                f"{what}: {name} never changes; the data need points with the {stage} stage "
                "at two or more angles"
            )


def check_loss(loss: str) -> str:
    if loss not in ROBUST_LOSSES:
        raise InputError(f"option --loss: {loss!r} is not one of {', '.join(ROBUST_LOSSES)}")
    return loss


def model_needs_meas(model: CalibrationModel) -> None:
    if not model.state.get("has_meas", False):
        raise InputError(
            f"this {model.method} model was calibrated without meas_x_deg/meas_y_deg, so it cannot "
            "correct measurement readings; recalibrate with the measurement sensor's columns"
        )


# --- vectorised 2-D Newton -------------------------------------------------------------------
def newton_2d(
    fun: Callable[
        [NDArray[np.float64], NDArray[np.float64]], tuple[NDArray[np.float64], NDArray[np.float64]]
    ],
    target_a: NDArray[np.float64],
    target_b: NDArray[np.float64],
    u0: NDArray[np.float64],
    v0: NDArray[np.float64],
    step_deg: float = 1e-5,
    tol_deg: float = 1e-10,
    max_iter: int = 30,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Solve fun(u, v) = (a, b) for every point at once (forward-difference Jacobian, 2x2 solves).

    All points iterate together: the cost is a handful of vectorised model evaluations, never a
    Python loop over points. Points that fail to converge raise InputError naming them.
    """
    u_deg = np.array(u0, dtype=float, copy=True)
    v_deg = np.array(v0, dtype=float, copy=True)
    want_a = np.asarray(target_a, dtype=float)
    want_b = np.asarray(target_b, dtype=float)
    for _ in range(max_iter):
        fa, fb = fun(u_deg, v_deg)
        ra, rb = fa - want_a, fb - want_b
        if np.all(np.abs(ra) < tol_deg) and np.all(np.abs(rb) < tol_deg):
            return u_deg, v_deg
        fua, fub = fun(u_deg + step_deg, v_deg)
        fva, fvb = fun(u_deg, v_deg + step_deg)
        j11, j21 = (fua - fa) / step_deg, (fub - fb) / step_deg
        j12, j22 = (fva - fa) / step_deg, (fvb - fb) / step_deg
        det = j11 * j22 - j12 * j21
        bad = ~np.isfinite(det) | (np.abs(det) < 1e-12)
        det = np.where(bad, 1.0, det)
        du = (j22 * ra - j12 * rb) / det
        dv = (-j21 * ra + j11 * rb) / det
        du = np.where(bad, 0.0, np.clip(du, -5.0, 5.0))
        dv = np.where(bad, 0.0, np.clip(dv, -5.0, 5.0))
        u_deg, v_deg = u_deg - du, v_deg - dv
    fa, fb = fun(u_deg, v_deg)
    worst = np.maximum(np.abs(fa - want_a), np.abs(fb - want_b))
    bad_rows = np.flatnonzero(~(worst < 1e-7))
    if bad_rows.size:
        rows = ", ".join(str(i + 1) for i in bad_rows[:5])
        raise InputError(
            f"no stage angles reach the wanted value at row(s) {rows} "
            f"(worst miss {np.nanmax(worst):.3g} deg): outside what the bench can do"
        )
    return u_deg, v_deg
