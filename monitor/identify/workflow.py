"""The identification of one axis, step by step (:func:`identify`; docs/method.md §8)."""

from __future__ import annotations

import math
import time

import numpy as np

from feedio.limits import SAMPLE_LIMITS
from kernels.adequacy import adequacy
from kernels.errors import ParameterError
from kernels.feed_drive import disturbance_to_force
from kernels.likelihood import PERIODIC_KINDS
from kernels.noise import white_noise

from .candidates import THESIS_DEFAULTS, Candidate, MethodResult, _Problem
from .periods import (
    _detected_alternative,
    _kernel_candidates,
    _periods_to_try,
    _spindle,
    _spindle_candidates,
    _weigh_alternative,
    periods_in_play,
)
from .progress import WorkPlan, planned_evaluations
from .regression import build_regression
from .result import Identification
from .rules import _bias_check, _choose, _efficiency_check, _invalidate
from .truth import _attach_truth

#: the longest command delay (samples) identify models when the adequacy test finds it
MAX_DELAY = 4


def identify(
    trial,
    *,
    form: str | None = None,
    period: float | None = None,
    spindle_rpm: float | None = None,
    sigma1: float | None = None,
    sigma2: float | None = None,
    gamma: float | None = None,
    tune: bool = True,
    method: str = "auto",
    coulomb: bool | None = None,
    omega: float | None = None,
    loop_gain: float | None = None,
    delay: int | None = None,
    progress=None,
) -> Identification:
    """Identify one axis: candidates, evidence, validity, choice (module docstring).

    ``progress(label, done, total)`` is called after each likelihood evaluation of the tuning (the bulk
    of the work; ``total`` is planned as the stages become known, :mod:`.progress`).
    ``coulomb=None`` keeps the Coulomb columns when the trial reverses direction (at least
    ``MIN_REVERSAL_SAMPLES`` samples beyond ±Ω each way) and drops them otherwise, with a
    note; ``coulomb=True`` insists (and fails on a trial without reversal). ``omega=None`` takes the
    dead band from the measurement noise (:mod:`.regression`). ``delay``: samples from a command to its force
    (None: 0, or the delay the adequacy test finds, modelled). ``method``: "auto",
    "ls" or "pl-lssvm". A bad argument raises :class:`~kernels.errors.ParameterError` naming it (``feedmon identify`` adds
    the flag, :mod:`feedmon.errors`).

    The steps, in order (each one function below):

    1. the signals, checked (:func:`_signals`), and the periods in play (:func:`periods_in_play`);
    2. the regression shared by all candidates (:func:`.regression.build_regression`): the dead band from
       the measurement noise, the friction columns, a process's mean force kept apart; its LS candidate;
    4. the periods to tune at: given, the spindle's, else found in the LS residual (:func:`_periods_to_try`);
    5. the kernel candidates, tuned by REML (:func:`_kernel_candidates`, :func:`_spindle_candidates`);
    6. with a given or spindle period, the period found in the data, tuned and weighed against it
       (:func:`_detected_alternative`, :func:`_weigh_alternative`);
    7. validity rules 2 and 3 and the choice (:func:`_rules_and_choice`), the fits, the low-speed check
       (:func:`_low_speed_note`) and what else the data say (:func:`_checks`).
    """
    started = time.perf_counter()
    form, exo, exo_name = _signals(trial, form, method)
    gain = _arguments(trial, form, sigma1, sigma2, gamma, loop_gain)
    plan = None if progress is None else WorkPlan(progress)
    run = _Run(trial, form, exo, exo_name, gain, dict(period=period, spindle_rpm=spindle_rpm, sigma1=sigma1,
                                                       sigma2=sigma2, gamma=gamma, tune=tune, method=method,
                                                       coulomb=coulomb, omega=omega), plan)
    if delay is not None and not (isinstance(delay, int) and not isinstance(delay, bool) and 0 <= delay <= 16):
        raise ParameterError(f"delay must be a whole number of samples 0 … 16, got {delay!r}", "delay")
    ident = run.once(delay=delay or 0)
    found = ident.adequacy
    if delay is None and found is not None and found.kind == "delay" and found.delay is not None \
            and 1 <= round(found.delay) <= MAX_DELAY and abs(found.delay - round(found.delay)) <= 0.3:
        delayed = run.once(delay=int(round(found.delay)))  # a delay it can estimate is modelled
        if delayed.model_result is not None and (delayed.adequacy is None or delayed.adequacy.adequate
                                                 or delayed.adequacy.explained < found.explained):
            delayed.notes.append(f"the model without the delay did not fit: {found.message}; modelled: the force "
                                 f"acts {delayed.delay} sample(s) after the command ([model] delay)")
            ident = delayed
    _attach_truth(ident, trial)
    ident.seconds = time.perf_counter() - started
    if plan is not None:
        plan.finish()
    return ident


class _Run:
    """One trial's identification at a given delay of the command (steps 2–7 of :func:`identify`)."""

    def __init__(self, trial, form, exo, exo_name, gain, options: dict, plan) -> None:
        self.trial, self.form, self.exo, self.exo_name, self.gain = trial, form, exo, exo_name, gain
        self.o, self.plan = options, plan

    def once(self, delay: int) -> Identification:
        trial, form, exo, gain, o = self.trial, self.form, self.exo, self.gain, self.o
        Ts, v = float(trial.meta.Ts), trial.v_meas
        psis, psi_source = periods_in_play(trial, o["period"], o["spindle_rpm"])
        notes: list[str] = []
        _note_unused_spindle(trial, o["period"], o["spindle_rpm"], psi_source, notes)
        reg = build_regression(form, v, exo, Ts, omega=o["omega"], coulomb=o["coulomb"],
                               spindle_rpm=trial.spindle_rpm, notes=notes, delay=delay)
        prob = _Problem(form, Ts, gain, reg.names, reg.T, reg.Z_id, reg.id_names, reg.y, exo, v, reg.omega,
                        reg.coulomb, gate=reg.process.active if reg.nuisance else None, keep=reg.keep)
        ls_c = prob.candidate("ls", None, None, None, {}, 0)
        psis, psi_source, k_period, detected = _periods_to_try(trial, reg.y - reg.Z_id @ ls_c.theta, Ts, prob.n * Ts,
                                                               psis, psi_source, notes)
        if self.plan is not None:
            spindle_changes = trial.spindle_angle is not None or trial.spindle_rpm is not None
            self.plan.plan(planned_evaluations(len(psis), spindle=2 if spindle_changes else 0, tune=o["tune"],
                                               alternative=bool(detected) and psi_source in ("given", "spindle")))
        found = _candidates(prob, ls_c, trial, psis, psi_source, k_period, detected, o, self.plan, notes)
        candidates, unused, alt_off, suggested, psis, psi_source = found
        chosen, refusal, pl_best, written = _rules_and_choice(candidates, ls_c, alt_off, o["method"])
        ls_res = prob.fit(ls_c, self.exo_name)
        pl_res = prob.fit(pl_best, self.exo_name) if pl_best is not None else None
        model_res = {id(ls_c): ls_res, id(pl_best): pl_res}.get(id(written)) if written is not None else None
        if written is not None and model_res is None:
            model_res = prob.fit(written, self.exo_name)
        _low_speed_note(reg, prob, model_res, notes)
        periodic = written if written is not None and written.kernel in PERIODIC_KINDS else None
        if gain is None and form == "velocity-loop":
            notes.append("loop gain K unknown: only J/K, B/K and the friction over K are identifiable "
                         "(give --loop-gain to get J and B)")
        ident = Identification(
            trial_path=str(trial.path), machine=trial.machine, axis=trial.axis, form=form, Ts=Ts,
            period=periodic.period if periodic is not None else (psis[0] if psis else None),
            period_source=psi_source, period_suggested=suggested, omega=reg.omega, coulomb=reg.coulomb,
            coulomb_note=reg.coulomb_note, rest=reg.rest, names=reg.names, loop_gain=gain,
            candidates=candidates + unused, chosen=chosen, ls=ls_res, pl=pl_res, model_result=model_res, y=reg.y,
            t=trial.t[1:], refusal=refusal, notes=notes,
        )
        ident.spindle = None if alt_off is not None else _spindle(trial)
        ident.periods = [float(p) for p in psis]
        ident.low_speed = reg.low_speed
        ident.min_speed = reg.min_speed
        ident.delay = reg.delay
        _checks(ident, reg, model_res, self.exo, v)
        return ident


def _candidates(prob: _Problem, ls_c: Candidate, trial, psis, psi_source, k_period, detected, o: dict, plan, notes):
    """Steps 5–6: the kernel candidates beside LS, the spindle-phase ones, the period found in the data
    weighed against a given one. Returns ``(candidates, unused, off_spindle, suggested, psis, psi_source)``,
    ``off_spindle`` the detected-period candidate that competes like any other (else None)."""
    init = {"sigma1": o["sigma1"] or THESIS_DEFAULTS["sigma1"], "sigma2": o["sigma2"] or THESIS_DEFAULTS["sigma2"],
            "gamma": o["gamma"] or THESIS_DEFAULTS["gamma"]}
    se_init = {"lengthscale": o["sigma1"], "gamma": o["gamma"]} if o["sigma1"] or o["gamma"] else None
    tuned_kw = dict(tune=o["tune"], progress=plan)
    kernel_candidates, psis = _kernel_candidates(prob, psis, psi_source, k_period, init, se_init, prob.n * prob.Ts,
                                                 notes, **tuned_kw)
    candidates = [ls_c, *kernel_candidates]
    alt = _detected_alternative(prob, psis, psi_source, detected, init, ls_c, trial, notes, **tuned_kw)
    candidates += _spindle_candidates(prob, trial, candidates, init, notes, **tuned_kw)
    suggested, unused, off = None, [], None
    if alt is not None:
        off_spindle, suggested = _weigh_alternative(alt, candidates, psi_source, o["spindle_rpm"], notes)
        if off_spindle:
            psi_source, psis, off = "detected", [alt.period], alt
        else:
            unused.append(alt)
    return candidates, unused, off, suggested, psis, psi_source


def _signals(trial, form: str | None, method: str) -> tuple[str, np.ndarray, str]:
    """Step 1: the input form (``form`` or the trial's) and its exogenous signal (``v_ref`` or ``u``)
    with its name, after checking ``method``, ``form`` and the record: every sample finite, no sequence gap."""
    if method not in ("auto", "ls", "pl-lssvm"):
        raise ParameterError(f"method must be 'auto', 'ls' or 'pl-lssvm', got {method!r}", "method")
    form = form or trial.meta.form
    if form not in ("velocity-loop", "force-input"):
        raise ParameterError(f"form must be 'velocity-loop' or 'force-input', got {form!r}", "form")
    if form == "force-input":
        if trial.u is None:
            raise ParameterError(f"{trial.path}: the force-input form needs a force command 'u', which the trial "
                                 "lacks; use form='velocity-loop'", "form")
        exo, exo_name = trial.u, "u"
    else:
        exo, exo_name = trial.v_ref, "v_ref"
    v = trial.v_meas
    bad = ~(np.isfinite(v) & np.isfinite(exo))
    if bad.any():
        raise ValueError(f"{trial.path}: {int(bad.sum())} sample(s) with missing or non-finite v_meas/{exo_name}, "
                         f"first at seq {int(trial.seq[np.argmax(bad)])}; identification needs a contiguous record")
    exo_max, exo_unit = (SAMPLE_LIMITS.u_max, "N") if exo_name == "u" else (SAMPLE_LIMITS.v_max, "m/s")
    absurd = (np.abs(v) > SAMPLE_LIMITS.v_max) | (np.abs(exo) > exo_max)
    if absurd.any():  # (least squares would call such a column "collinear")
        k = int(np.argmax(absurd))
        raise ValueError(f"{trial.path}: {int(absurd.sum())} sample(s) with an absurd magnitude, first at seq "
                         f"{int(trial.seq[k])} (v_meas = {v[k]:.6g} m/s, {exo_name} = {exo[k]:.6g} {exo_unit}; limits "
                         f"{SAMPLE_LIMITS.v_max:g} m/s, {exo_max:g} {exo_unit}): a recording or unit fault; identify a window "
                         "without it (trial.window(start, end)) or fix the file")
    Ts = float(trial.meta.Ts)
    steps = np.diff(trial.seq)
    if steps.size and np.any(steps != 1):
        k = int(np.argmax(steps != 1))
        raise ValueError(f"{trial.path}: sequence gap after seq {int(trial.seq[k])}; identify a contiguous segment")
    dt = float(np.median(np.diff(trial.t))) if trial.t.size > 1 else Ts
    if not math.isclose(dt, Ts, rel_tol=0.01):  # β, J, B are of the metadata's Ts: a wrong one scales them silently
        raise ValueError(f"{trial.path}: the samples are {dt:.6g} s apart but the trial's metadata give Ts = {Ts:.6g} s; "
                         "the model is of one sampling time — re-create the trial with the right one (the importer's Ts)")
    return form, exo, exo_name


def _note_unused_spindle(trial, period: float | None, spindle_rpm: float | None, psi_source: str,
                         notes: list[str]) -> None:
    """A note when the trial's metadata give a spindle speed whose period the record cannot hold (under two
    samples, or over half the record): :func:`periods_in_play` then leaves it out."""
    meta_rpm, Ts, duration = trial.meta.spindle_rpm, float(trial.meta.Ts), len(trial.v_meas) * float(trial.meta.Ts)
    if period is None and spindle_rpm is None and psi_source != "spindle" and meta_rpm and math.isfinite(meta_rpm):
        notes.append(f"the spindle period 60/{meta_rpm:g} rpm = {60.0 / meta_rpm:.6g} s (trial metadata) is "
                     + (f"shorter than two samples (Ts = {Ts:.6g} s): its lines are folded at half the sample rate"
                        if 60.0 / meta_rpm < 2.0 * Ts else f"longer than half the record ({duration:.6g} s)")
                     + "; not used as the disturbance period (give a period to insist on one)")


def _arguments(trial, form, sigma1, sigma2, gamma, loop_gain) -> float | None:
    """The hyperparameters given checked; the loop gain K (N·s/m) of the velocity-loop form (None: unknown)."""
    for name, value in (("sigma1", sigma1), ("sigma2", sigma2), ("gamma", gamma)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ParameterError(f"{name} must be a positive number, got {value!r}", name)
    gain = None if form == "force-input" else (loop_gain if loop_gain is not None else trial.meta.loop_gain)
    if gain is not None and not (math.isfinite(gain) and gain > 0):
        if loop_gain is not None:
            raise ParameterError(f"loop_gain must be a positive number (N·s/m), got {gain!r}; give the velocity-loop "
                                 "gain K, or leave it out to identify J/K and B/K", "loop_gain")
        raise ValueError(f"{trial.path}: the trial's loop_gain must be a positive number (N·s/m), got {gain!r}; give "
                         "the velocity-loop gain K (loop_gain), or leave it out to identify J/K and B/K")
    return gain


def _rules_and_choice(candidates: list[Candidate], ls_c: Candidate, off_spindle: Candidate | None, method: str):
    """Validity rules 2 and 3, then the choice (:func:`_choose`); ``off_spindle``: the period found in the data
    that competes like any other (checked in :func:`_detected_alternative`)."""
    for c in candidates[1:]:  # validity rule 2: determined at least as well as LS
        _invalidate(c, _efficiency_check(c, ls_c))
    if off_spindle is not None:
        candidates.append(off_spindle)
    eligible = [c for c in candidates if c.eligible]
    witnesses = [c for c in eligible if c is ls_c or _efficiency_check(c, ls_c) is None]
    for c, why in [(c, _bias_check(c, witnesses)) for c in eligible]:  # validity rule 3
        _invalidate(c, why)
    return _choose(candidates, method)


def _checks(ident: Identification, reg, model_res: MethodResult | None, exo: np.ndarray, v: np.ndarray) -> None:
    """What the data say beyond β: the measurement noise (of the written model's residual), where a process
    acts and whether its mean force is kept out of friction and offset, whether the rigid model explains
    the data at all (:mod:`kernels.adequacy`; the JSON ``checks``)."""
    noise = reg.noise
    if model_res is not None:
        c = model_res.candidate
        resid = reg.y - reg.Z_spec @ c.beta  # the monitor's residual v(k) = v_m(k+1) − βᵀz(k)
        try:
            noise = white_noise(resid, pole=min(max(c.pole, -0.999), 1.0))
        except ParameterError:
            pass
    ident.noise = noise
    ident.offset_separated = reg.offset_separated
    if model_res is not None and not reg.nuisance and model_res.candidate.kernel == "locally_periodic_zero_mean":
        ident.offset_separated = False  # the zero-mean kernel leaves the disturbance's mean to the offset
    ident.adequacy = _adequacy(ident, reg, model_res, exo, v)
    process = None
    if reg.process is not None:
        process = {"share": float(np.mean(reg.process.active)), "nuisance": list(reg.nuisance)}
    ident.checks = {"noise": None if noise is None else noise.to_json(), "omega": reg.omega, "process": process,
                    "offset_separated": ident.offset_separated, "offset_note": reg.offset_note,
                    "low_speed": None if ident.low_speed is None else ident.low_speed.to_json(),
                    "law_holds_above": None if reg.cut is None else reg.cut.to_json(),
                    "left_out": 0 if reg.keep is None else int(np.sum(~reg.keep)), "min_speed": reg.min_speed,
                    "adequacy": None if ident.adequacy is None else ident.adequacy.to_json(), "delay": reg.delay}


def _adequacy(ident: Identification, reg, model_res: MethodResult | None, exo: np.ndarray, v: np.ndarray):
    """The model-adequacy test (:func:`kernels.adequacy.adequacy`) on the written model's residual after its
    disturbance model; a note naming what the rigid model leaves."""
    if model_res is None:
        return None
    c = model_res.candidate
    e = reg.y - np.where(np.isfinite(model_res.prediction), model_res.prediction, reg.Z_spec @ c.beta)
    vm = v[:-1]
    command = exo[:-1] - vm if ident.form == "velocity-loop" else exo[:-1]
    try:
        found = adequacy(e, command, vm, ident.Ts, gain=float(c.beta[0]), pole=float(c.pole))
    except ParameterError:
        return None
    if not found.adequate:
        ident.notes.append(f"the rigid model does not fit this drive: {found.message}")
    return found


def _low_speed_note(reg, prob: _Problem, res: MethodResult | None, notes: list[str]) -> None:
    """A note when the friction law does not hold near standstill (:mod:`kernels.low_speed`, found in the
    shared regression): its size in N (with the written model's force gain), the speed, the samples left
    out of the fit (a Stribeck rise) and the speed above which the monitor learns β."""
    check = reg.low_speed
    if check is None or not check.significant or res is None:
        return
    scalable = prob.form == "force-input" or prob.gain is not None

    def force(departure: float) -> str:  # a departure of the residual, in velocity per sample, as a friction
        if not scalable:
            return f"{'above' if departure < 0 else 'below'} (by {abs(departure):.3g} m/s per sample; give " \
                   "--loop-gain for N)"
        delta = float(disturbance_to_force(prob.form, res.beta, departure, gain=prob.gain))
        return f"{abs(delta):.3g} N {'above' if delta > 0 else 'below'}"

    if reg.cut is not None:
        what = (f"the friction law (Coulomb + viscous) does not hold near standstill: it holds above "
                f"{reg.cut.speed:.3g} m/s (found in the data), below it the friction is on average "
                f"{force(reg.cut.departure)} the law ({100 * reg.cut.share:.0f} % of the motion)")
        if reg.keep is not None:
            notes.append(f"{what}: a Stribeck rise — those samples are left out of the batch fit, and the monitor "
                         f"learns β only above min_speed = {reg.min_speed:.3g} m/s")
        else:
            notes.append(f"{what}: a gradual onset, kept in the batch fit (it bends β little); the monitor learns β "
                         f"only above min_speed = {reg.min_speed:.3g} m/s")
        return
    what = (f"the friction law (Coulomb + viscous) does not hold near standstill: below about {check.speed:.3g} m/s "
            f"the friction is {force(-check.amplitude)} the law (log-likelihood gain {check.gain:.0f})")
    if check.local:
        notes.append(f"{what}; the monitor learns β only above min_speed = {reg.min_speed:.3g} m/s "
                     f"({100 * check.share:.0f} % of the motion is slower)")
    else:
        notes.append(f"{what}, but {100 * check.share:.0f} % of the motion is that slow: not a low-speed effect "
                     "to leave out (min_speed stays 0); it may be a disturbance that follows the feed")
