"""The kinematic chain of docs/models.md §2 fitted by nonlinear least squares, with the measurement
sensor's mounting fitted against the reference; the bench's hardware is an input."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from service.calibration.methods.stage import reference
from service.calibration.methods.stage.base import (
    FIT_REQUIRED,
    Columns,
    StageMethod,
    ThreeWay,
    bench_state,
    meas_dof,
    meas_reading_noise,
    meas_sign,
    noise_state,
    reading_noise_of,
    stage_hardware,
    stage_model,
    targets,
    used_columns,
)
from service.calibration.methods.stage.chain import (
    EFFECT_PARAMS,
    REFERENCE_EFFECTS,
    ChainFit,
    ChainModel,
    MeasFit,
    fit_chain,
    fit_meas,
    unit_of,
)
from service.calibration.methods.stage.common import (
    MEAS_COLUMNS,
    MEAS_NAMES,
    MEAS_PARAMS,
    check_loss,
    columns,
    has_meas,
    meas_inverse_gum,
    mirror_note,
    model_needs_meas,
    require_spread,
)
from service.calibration.model import (
    CalibrationModel,
    FitInfo,
    ModelState,
    Parameter,
    ReferenceErrorsState,
    residual_summary,
)
from service.calibration.registry import FitOptions
from service.calibration.stage_effect_fit import StagePoints, param_label
from service.calibration.uncertainty import coverage_factor
from service.errors import InputError
from service.io.columns import K_OUTPUTS
from service.physics.stage import StageBench


class KinematicMethod(StageMethod):
    """The chain of docs/models.md §2 fitted by nonlinear least squares; the measurement sensor's
    own mounting fitted against the reference. Parameters the points cannot separate are held and
    said so."""

    name = "kinematic"

    def fit(self, data: Columns, options: FitOptions) -> CalibrationModel:
        sx, sy, rx, ry = columns(data, FIT_REQUIRED)
        loss = check_loss(options.loss)
        require_spread(sx, sy, 5, "the kinematic model")
        bench, source, stated = stage_hardware(options)
        mismatch = _pulse_mismatch(bench, stated, sx, sy)
        added = [str(effect_name) for effect_name in options.extra.get("effects", ())]
        pts, time_origin = _stage_points(data, added)
        chain = fit_chain(
            bench,
            pts,
            rx,
            ry,
            loss=loss,
            periodic=bool(options.extra.get("periodic_error", False)),
            max_nfev=int(options.extra.get("max_nfev", 200)),
            effects=added,
            worm_axes=tuple(options.extra.get("worm_axes", ("x", "y"))),
        )
        params = _chain_parameters(chain)
        cov_names = [param_label(k) for k in chain.keys]
        blocks = [chain.covariance]
        residuals = dict(chain.residuals)
        notes = _chain_notes(chain, loss, f"bench: {bench.describe()}; {source}", mismatch)
        fit_info: FitInfo = {
            "n_points": int(sx.size),
            "chain": {
                "dof": chain.dof,
                "sigma_deg": chain.sigma,
                "converged": chain.converged,
                "nfev": chain.nfev,
                "loss": loss,
                "scaled_jacobian_singular_values": chain.singular_values.tolist(),
            },
        }
        notes += _effect_notes(chain, added)
        fit_info["undetermined_effects"] = dict(chain.undetermined)
        fit_info["priors"] = {param_label(k): why for k, why in chain.priors.items()}
        if worm := periodic_summary(chain):
            fit_info["periodic_error"] = worm
            notes += _worm_notes(worm)
        state: ModelState = {
            "has_meas": has_meas(data),
            **bench_state(bench, source),
            "chain_parameters": [param_label(k) for k in list(chain.keys) + list(chain.fixed)],
            "approach": [1.0, 1.0],
        }
        ref_effects = _reference_effects(chain)
        if ref_effects:
            state[reference.STATE_KEY] = _reference_state(ref_effects, bench, data, time_origin)
        if has_meas(data):
            # the chain's residuals are prediction − reference reading, per point as the data's
            ref_minus_stage = -np.array(
                [chain.residuals["ref_x_deg"], chain.residuals["ref_y_deg"]]
            )
            meas = _add_measurement_sensor(
                data,
                options,
                loss,
                (rx, ry),
                bool(ref_effects),
                params,
                state,
                notes,
                ref_minus_stage,
            )
            cov_names += meas.names
            blocks.append(meas.covariance)
            residuals.update(meas.residuals)
            fit_info["meas"] = {
                "dof": meas.dof,
                "covariance_dof": meas.covariance_dof,
                "sigma_deg": meas.sigma,
                "nfev": meas.nfev,
            }
        else:
            notes.append("no meas_x_deg/meas_y_deg columns: this model can level but not correct")
        notes.append(
            "the covariance is block-diagonal between the chain and the measurement sensor "
            "(separate fits)"
        )
        return stage_model(
            self.name,
            used_columns(data),
            params,
            notes,
            covariance_names=cov_names,
            covariance=_block_diagonal(blocks),
            residuals=residual_summary(residuals, "deg"),
            fit=fit_info,
            state=state,
            options={"loss": loss, **({"effects": added} if added else {})},
        )

    @staticmethod
    def chain_model(model: CalibrationModel) -> ChainModel:
        bench = StageBench(**model.state.get("bench", {}))
        values = {}
        for name in model.state.get("chain_parameters", []):
            effect, param = name.split(".", 1)
            values[(effect, param)] = model.value(name)
        return ChainModel.from_values(bench, values)

    def commands(
        self, model: CalibrationModel, data: Columns
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        tx, ty = targets(data)
        ap = model.state.get("approach", [1.0, 1.0])
        dx = np.asarray(data.get("dir_x", ap[0]), dtype=float)
        dy = np.asarray(data.get("dir_y", ap[1]), dtype=float)
        chain = self.chain_model(model)
        x, y = chain.level(tx, ty, dx, dy)
        return x, y

    def correct(self, model: CalibrationModel, data: Columns) -> dict[str, NDArray[np.float64]]:
        model_needs_meas(model)
        sign = np.asarray(model.state.get("meas_sign", [1.0, 1.0]), dtype=float)
        mx, my = columns(data, MEAS_COLUMNS)
        sigma, noise_dof = reading_noise_of(model)
        tilt_x, tilt_y, gx, gy = meas_inverse_gum(
            model.values(MEAS_NAMES),
            model.cov_of(list(MEAS_NAMES)),
            sign,
            mx,
            my,
            sigma,
            meas_dof(model),
            noise_dof,
        )
        # U = k·u_c, as Propagated.expanded
        kx, ky = coverage_factor(gx.dof_eff), coverage_factor(gy.dof_eff)
        return {
            "tilt_x_deg": tilt_x,
            "tilt_y_deg": tilt_y,
            "u_tilt_x_deg": kx * gx.u,
            "u_tilt_y_deg": ky * gy.u,
            K_OUTPUTS[0]: np.broadcast_to(kx, tilt_x.shape),
            K_OUTPUTS[1]: np.broadcast_to(ky, tilt_y.shape),
        }


def _time_origin(data: Columns, added: list[str]) -> float | None:
    """Where a fitted time drift is zero: the time of the first point (POSIX seconds, as stored
    points carry it)."""
    if "time_drift" not in added:
        return None
    if "t_s" not in data or not np.all(np.isfinite(np.asarray(data["t_s"], dtype=float))):
        raise InputError(
            "time_drift: the points carry no t_s column (or it has gaps); a drift is fitted on the "
            "time of every point"
        )
    return float(np.min(np.asarray(data["t_s"], dtype=float)))


def _pulse_mismatch(
    bench: StageBench, stated: bool, sx: NDArray[np.float64], sy: NDArray[np.float64]
) -> str | None:
    """Commands that are not whole pulses: refused on an assumed bench, returned on a stated one."""
    mismatch = bench.pulse_mismatch(sx, sy)
    if not stated and mismatch is not None:
        raise InputError(
            f"{mismatch}. The kinematic model depends on the bench's hardware and none was "
            "stated "
            f"({bench.describe()} assumed): give the bench the data came from with --bench FILE"
        )
    return mismatch


def _stage_points(data: Columns, added: list[str]) -> tuple[StagePoints, float | None]:
    """The points the chain is fitted on (times from the drift's origin) and that origin."""
    pts = StagePoints.from_columns(data)
    time_origin = _time_origin(data, added)
    if time_origin is not None and pts.t_s is not None:
        pts.t_s = pts.t_s - time_origin
    if "temperature_drift" in added and (pts.temp_c is None or not np.all(np.isfinite(pts.temp_c))):
        raise InputError(
            "temperature_drift: the points carry no temp_c column (or it has gaps); a "
            "temperature effect is fitted on the temperature of every point"
        )
    return pts, time_origin


def _chain_parameters(chain: ChainFit) -> dict[str, Parameter]:
    """The chain's fitted parameters, then those held at zero with why."""
    params: dict[str, Parameter] = {}
    for k, value in zip(chain.keys, chain.values):
        params[param_label(k)] = Parameter(float(value), unit_of(k))
    for k, why in chain.fixed.items():
        params[param_label(k)] = Parameter(0.0, unit_of(k), fixed=True, note=why)
    return params


def _chain_notes(chain: ChainFit, loss: str, bench_note: str, mismatch: str | None) -> list[str]:
    """The chain's notes: model and gauge, the bench, what is held, correlated or given a prior."""
    notes = [
        (
            "chain (docs/models.md §2): desk · Rot(lower axis, y) · Rot(upper axis, x) · "
            "top · reference seat · reference yaw, with stage scale and backlash on the "
            "commands; fitted to ref_x_deg/ref_y_deg with scipy.optimize.least_squares "
            f"(loss {loss}); the reference is the lab's standard, so its own zero, scale and "
            "non-orthogonality are not fitted (its readings are the table tilt)"
        ),
        (
            "gauge: a common rotation of desk, stage axes and table top changes no reading, "
            "so one parameter of each of (lower yaw, perpendicularity, ref yaw), (desk x, "
            "lower pitch, top x), (desk y, upper pitch, top y) and the reference seat "
            "(composes with the top) is held; the fitted perpendicularity and ref yaw are "
            "then relative to the lower axis, desk tilts include the stages' zero offsets"
        ),
    ]
    notes.append(bench_note)
    if mismatch is not None:
        notes.append(
            "the commands are not whole pulses of the stated bench "
            f"({mismatch.split(':')[0]}): taken "
            "as requested angles, executed as the nearest whole pulses"
        )
    notes += [f"{param_label(k)}: {why}" for k, why in chain.fixed.items()]
    with_prior = {param_label(k) for k in chain.priors}
    notes += [
        f"{first} and {second} are correlated {corr:+.5f} (near-degenerate: they differ only by "
        "1 - cos of the other stage's angle; kept, since holding either leaves that difference "
        "as model error; "
        + (
            "what the points leave open is held by the drawings' prior below)"
            if {first, second} & with_prior
            else "their sum is well determined and both are stated with the uncertainty the "
            "points give)"
        )
        for first, second, corr in chain.correlations
    ]
    notes += [f"{param_label(k)}: {why}" for k, why in chain.priors.items()]
    return notes


def _effect_notes(chain: ChainFit, added: list[str]) -> list[str]:
    """What the notes say of the effects a record added: fitted with the rest, or undetermined."""
    notes = []
    if added:
        notes.append(
            f"effects added to the chain: {', '.join(added)} (their parameters fitted with "
            "the rest, as far as these points determine them)"
        )
    for effect, why in chain.undetermined.items():
        notes.append(
            f"{effect} was asked for, but these points determine none of its parameters ({why})"
        )
    return notes


def _worm_notes(worm: dict[str, dict[str, float]]) -> list[str]:
    """Each fitted worm's periodic error in the registry's terms, with standard uncertainties."""
    return [
        f"periodic error of the {ax} stage's worm: amplitude "
        f"{terms['amplitude_deg']:.3g} ± {terms['u_amplitude_deg']:.2g} deg, phase "
        f"{terms['phase_deg']:.1f} ± {terms['u_phase_deg']:.2g} deg (from its sine/cosine "
        "pair, standard uncertainties)"
        for ax, terms in worm.items()
    ]


def _reference_effects(chain: ChainFit) -> tuple[str, ...]:
    """The reference sensor's own reading errors among what the chain fitted."""
    return tuple(
        effect_name
        for effect_name in REFERENCE_EFFECTS
        if any(k in chain.keys for k in EFFECT_PARAMS[effect_name])
    )


def _reference_state(
    ref_effects: tuple[str, ...], bench: StageBench, data: Columns, time_origin: float | None
) -> ReferenceErrorsState:
    """The state's record of the reference model: effects, temperature and time origins, span."""
    span = None if time_origin is None else float(np.ptp(np.asarray(data["t_s"], dtype=float)))
    return reference.state_of(ref_effects, bench.temp_ref_c, time_origin, span)


def _add_measurement_sensor(
    data: Columns,
    options: FitOptions,
    loss: str,
    ref_xy: tuple[NDArray[np.float64], NDArray[np.float64]],
    models_reference: bool,
    params: dict[str, Parameter],
    state: ModelState,
    notes: list[str],
    ref_minus_stage: NDArray[np.float64],
) -> MeasFit:
    """Fit the measurement sensor against the table tilt, adding its parameters, state and notes;
    `ref_minus_stage` (2 x n) is the chain's residual, the third instrument of the reading noise's
    three-way estimate."""
    sign, how = meas_sign(data, options)
    mx, my = columns(data, MEAS_COLUMNS)
    ref_tx, ref_ty = ref_xy
    if models_reference:
        # the measurement sensor is fitted against the table tilt, which the reference reads with
        # the errors this record models: against its readings with those taken out
        errors = reference.reference_errors(_with_values(params, state))
        assert errors is not None
        ref_tx, ref_ty = reference.true_reading(
            errors, ref_tx, ref_ty, data.get("temp_c"), data.get("t_s")
        )
        notes.append(
            "reference sensor: the record models its own reading errors "
            f"({errors.describe()}); the measurement sensor is fitted against its "
            "readings with them taken out (the table tilt), and everything reported "
            "from the reference goes through them"
        )
    meas = fit_meas(ref_tx, ref_ty, mx, my, sign, loss=loss)
    units = {meas_param[0]: meas_param[1] for meas_param in MEAS_PARAMS}
    for name, value in zip(MEAS_NAMES, meas.values):
        fixed = name in meas.fixed
        params[name] = Parameter(
            float(value), units[name], fixed=fixed, note=meas.fixed.get(name, "")
        )
    # the parameters' part of a corrected tilt carries the covariance's degrees of freedom (per
    # axis)
    state.update(
        {
            "meas_sign": sign.tolist(),
            "meas_sigma_deg": meas.sigma,
            "meas_dof": meas.covariance_dof,
        }
    )
    # the fit's residuals are prediction − reading in the sensor's own frame: −sign × them is
    # meas − ref in the reference's
    meas_minus_ref = -sign[:, None] * np.array(
        [meas.residuals["meas_x_deg"], meas.residuals["meas_y_deg"]]
    )
    noise = meas_reading_noise(
        data, options, meas.sigma, meas.dof, sign, ThreeWay(meas_minus_ref, ref_minus_stage)
    )
    state.update(noise_state(noise))
    notes.append(
        "measurement sensor: zero offsets, scales, yaw, non-orthogonality and seat "
        "tilt, all relative to the reference sensor's frame (the table-tilt frame), "
        "fitted to meas_* against ref_* (no stage parameter enters, stage repeatability "
        "stays out); correct inverts it in closed form; the uncertainty of a corrected "
        "tilt from its covariance and the noise of one measurement reading, "
        f"{noise.sigma_deg:.3g} deg: {noise.source}"
    )
    notes += [f"{n}: {why}" for n, why in meas.fixed.items()]
    notes += [
        f"{first} and {second} are correlated {corr:+.5f} (near-degenerate: they differ only by "
        "1 - cos of the tilt; kept, their sum is well determined)"
        for first, second, corr in meas.correlations
    ]
    if (mn := mirror_note(sign)) is not None:
        notes.append(f"{mn} ({how})")
    return meas


def _block_diagonal(blocks: list[NDArray[np.float64]]) -> NDArray[np.float64]:
    """The separate fits' covariances as one matrix, zero between them."""
    k = sum(block.shape[0] for block in blocks)
    cov = np.zeros((k, k))
    i = 0
    for block in blocks:
        cov[i : i + block.shape[0], i : i + block.shape[0]] = block
        i += block.shape[0]
    return cov


def _with_values(params: dict[str, Parameter], state: ModelState) -> CalibrationModel:
    """A model of just these parameters and state (to read its reference model before the model is
    made)."""
    return CalibrationModel("stage", "kinematic", [], params, state=state)


def periodic_summary(chain: ChainFit) -> dict[str, dict[str, float]]:
    """Per stage whose worm the chain fitted: the periodic error's amplitude and phase (the
    registry's terms) with standard uncertainties, propagated from the sine/cosine pair's
    covariance."""
    out = {}
    for ax in ("x", "y"):
        ks, kc = ("periodic_error", f"{ax}_sin_deg"), ("periodic_error", f"{ax}_cos_deg")
        if ks not in chain.keys or kc not in chain.keys:
            continue
        i, j = chain.keys.index(ks), chain.keys.index(kc)
        sin_amp, cos_amp = float(chain.values[i]), float(chain.values[j])
        cov = chain.covariance[np.ix_([i, j], [i, j])]
        amp = float(np.hypot(sin_amp, cos_amp))
        if amp == 0.0:
            continue
        g_amp = np.array([sin_amp, cos_amp]) / amp
        g_phase = np.array([-cos_amp, sin_amp]) / amp**2
        var_amp, var_phase = float(g_amp @ cov @ g_amp), float(g_phase @ cov @ g_phase)
        out[ax] = {
            "amplitude_deg": amp,
            "u_amplitude_deg": float(np.sqrt(max(var_amp, 0.0))),
            "phase_deg": float(np.degrees(np.arctan2(cos_amp, sin_amp))),
            "u_phase_deg": float(np.degrees(np.sqrt(max(var_phase, 0.0)))),
        }
    return out


KINEMATIC = KinematicMethod()
