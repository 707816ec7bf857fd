"""The disturbance periods in play and the kernel candidates tuned at them (docs/method.md §8, "Period",
"Spindle-phase candidate")."""

from __future__ import annotations

import contextlib
import math

import numpy as np

from kernels import LocallyPeriodic
from kernels.errors import ParameterError
from kernels.likelihood import PERIODIC_KINDS
from kernels.period import MIN_CYCLES, detect_periods, harmonically_related, sampled_harmonic
from kernels.spindle_phase import MAX_HOLE, phase_segments, segment_tolerance, spindle_phase

from .. import online_settings as OS
from .candidates import (
    MAX_PERIOD_FRACTION,
    SPINDLE_SHARE,
    SUGGEST_MARGIN,
    Candidate,
    _Problem,
    _TunedBeside,
    busiest_window,
)
from .rules import _efficiency_check, _invalidate

#: the most samples the period search reads (its harmonic-sum periodogram costs more than O(N log N)): the
#: window with the most disturbance, ~200 s at 333 Hz — ample resolution for any period it may find
PERIOD_WINDOW = 65_536


def _check_period(psi: float, what: str, Ts: float, duration: float, parameter: str | None = None) -> float:
    """``psi`` checked against the record; ``parameter``: the argument it comes from (the error is then
    a :class:`~kernels.errors.ParameterError` naming it), None for a period read from the trial."""
    def bad(message: str) -> ValueError:
        return ValueError(message) if parameter is None else ParameterError(message, parameter)

    if not (math.isfinite(psi) and psi > 0):
        raise bad(f"{what} must give a positive period in s, got {psi!r}")
    if psi < 2.0 * Ts:
        raise bad(f"{what}: period {psi:.6g} s is shorter than two samples (Ts = {Ts:.6g} s); "
                  "a disturbance that fast cannot be seen at this sample rate")
    if psi > MAX_PERIOD_FRACTION * duration:
        raise bad(f"{what}: period {psi:.6g} s is longer than half the record ({duration:.6g} s); "
                  "a periodic disturbance needs at least two periods in the trial")
    return float(psi)


def periods_in_play(trial, period: float | None = None, spindle_rpm: float | None = None) -> tuple[list[float], str]:
    """The disturbance period(s) ψ (s) and their source, in this order: ``period`` ("given"), the
    spindle speed ``spindle_rpm`` / trial metadata / the samples' ``spindle_rpm`` column
    ("spindle": ψ = 60/rpm, the spindle period, right with tool runout; every speed holding at
    least ``SPINDLE_SHARE`` of the samples), else ``([], "none")`` — the caller then looks for
    one in the data ("detected").
    """
    if period is not None and spindle_rpm is not None:
        raise ParameterError("period and spindle_rpm both give the disturbance period; give one of them",
                             "period", "spindle_rpm")
    Ts = float(trial.meta.Ts)
    duration = len(trial.t) * Ts
    if period is not None:
        return [_check_period(float(period), "period", Ts, duration, "period")], "given"
    if spindle_rpm is not None:
        if not (math.isfinite(spindle_rpm) and spindle_rpm > 0):
            raise ParameterError(f"spindle_rpm must be positive, got {spindle_rpm!r}", "spindle_rpm")
        return [_check_period(60.0 / spindle_rpm, "spindle_rpm", Ts, duration, "spindle_rpm")], "spindle"
    meta_rpm = trial.meta.spindle_rpm
    if meta_rpm is not None and math.isfinite(meta_rpm) and meta_rpm > 0 and (
            2.0 * Ts <= 60.0 / meta_rpm <= MAX_PERIOD_FRACTION * duration):  # else as the samples' speeds below
        return [60.0 / meta_rpm], "spindle"
    col = getattr(trial, "spindle_rpm", None)
    if col is not None:
        rpm = np.asarray(col, dtype=np.float64)
        rpm = rpm[np.isfinite(rpm) & (rpm > 0)]
        if rpm.size >= SPINDLE_SHARE * len(trial.t):
            levels, counts = np.unique(np.round(rpm, 0), return_counts=True)
            keep = [float(lv) for lv, c in zip(levels, counts) if c >= SPINDLE_SHARE * len(trial.t)]
            periods = []
            for lv in sorted(keep, key=lambda x: -counts[np.searchsorted(levels, x)]):
                psi = 60.0 / lv
                if 2.0 * Ts <= psi <= MAX_PERIOD_FRACTION * duration and not any(
                        abs(psi - q) <= 0.005 * q for q in periods):
                    periods.append(psi)
            if periods:
                return periods, "spindle"
    return [], "none"




def _periods_to_try(trial, ls_resid: np.ndarray, Ts: float, duration: float, psis: list[float], psi_source: str,
                    notes: list[str]) -> tuple[list[float], str, int, list]:
    """Step 4: the periods the kernel candidates are tuned at, their source and ``k_period`` (1 when the
    period was found in the data: one more fitted hyperparameter), and the periods found in the LS
    residual ``ls_resid`` (within two samples and :data:`MAX_PERIOD_FRACTION` of the record). Without a
    given or spindle period the strongest one found is used; notes say so, say when none is found, and
    when a given period is locked to the motion."""
    ref = trial.v_ref[:-1] if trial.v_ref is not None and np.all(np.isfinite(trial.v_ref)) else None
    a, b = busiest_window(ls_resid, PERIOD_WINDOW)
    if b - a < ls_resid.size:
        notes.append(f"periods searched in the {(b - a) * Ts:.0f} s of the record with the most disturbance "
                     f"({a * Ts:.0f} … {b * Ts:.0f} s)")
    try:
        detected, motion = detect_periods(ls_resid[a:b], Ts, reference=None if ref is None else ref[a:b])
    except ValueError:
        detected, motion = [], None
    detected = [d for d in detected if 2.0 * Ts <= d.period <= min(duration / MIN_CYCLES, MAX_PERIOD_FRACTION * duration)]
    k_period = 0
    if not psis and detected:
        psis, psi_source, k_period = [detected[0].period], "detected", 1
        notes.append(f"period ψ = {detected[0].period:.6g} s found in the LS residual (harmonic-sum score "
                     f"{detected[0].score:.0f} over {detected[0].harmonics} harmonics)")
    elif not psis:
        notes.append("no periodic disturbance found in the LS residual" +
                     (f" (the motion itself repeats every {motion:.4g} s)" if motion else "") +
                     "; give --period or --spindle-rpm if there is one")
    if motion is not None and psi_source in ("given", "spindle"):
        for psi in psis:
            if harmonically_related(psi, motion, max_ratio=4):
                notes.append(f"ψ = {psi:.6g} s is locked to the motion, which repeats every {motion:.4g} s: a "
                             "disturbance with that period cannot be told from the drive's response to the motion")
    return psis, psi_source, k_period, detected


def _kernel_candidates(prob: _Problem, psis: list[float], psi_source: str, k_period: int, init: dict,
                       se_init: dict | None, duration: float, notes: list[str], *, tune: bool,
                       progress) -> tuple[list[Candidate], list[float]]:
    """Step 5: the squared-exponential candidate (tuned on a second thread, :class:`_TunedBeside`; listed
    first) and, at each period, the locally periodic candidate (with its multiples when the period was
    found in the data: :func:`_harmonic_alternatives`) followed by the zero-mean one, started from its
    optimum. Returns the candidates and the periods they were tuned at."""
    tuned_kw = dict(tune=tune, progress=progress)
    if tune:  # it depends on no other candidate: tuned on a second thread beside the periodic ones
        beside = _TunedBeside(prob, "squared_exponential", None, se_init, k_extra=0, label="squared exponential",
                              **tuned_kw)
    else:
        beside = contextlib.nullcontext()
        notes.append("--no-tune: the squared-exponential candidate has no given or thesis hyperparameters "
                     "and is left out")
    first, periodic, tuned_psis = [], [], []
    with beside:
        for psi in psis:
            cand = prob.tuned("locally_periodic", psi, init, k_extra=k_period,
                              label=f"locally periodic ψ = {psi:.6g} s", **tuned_kw)
            if psi_source == "detected" and tune:
                cand = _harmonic_alternatives(prob, cand, psi, duration, progress)
            periodic.append(cand)
            zero_init = dict(cand.hyperparameters) if tune else init
            periodic.append(prob.tuned("locally_periodic_zero_mean", cand.period, zero_init,
                                       k_extra=cand.k - 3 if tune else k_period,
                                       label=f"zero-mean locally periodic ψ = {cand.period:.6g} s", refine=True,
                                       **tuned_kw))
            tuned_psis.append(cand.period)
        if tune:
            first.append(beside.result())  # listed before the periodic ones, as when tuned in turn
    return first + periodic, tuned_psis


def _detected_alternative(prob: _Problem, psis: list[float], psi_source: str, detected: list, init: dict,
                          ls: Candidate, trial, notes: list[str], *, tune: bool, progress) -> Candidate | None:
    """Step 6a: with a given or spindle period, the locally periodic candidate at the period found in the
    data when it is more than 2 % from every period tuned (validity rule 2 applied), else None — also when
    it is a (folded) harmonic of the spindle's line, which the kernel at the spindle period has (a note says
    so; tuning it would show nothing the choice could use)."""
    if psi_source not in ("given", "spindle") or not detected:
        return None
    found = detected[0]
    if any(abs(psi - found.period) <= 0.02 * found.period for psi in psis):
        return None
    if _spindle_harmonic(found.period, trial, psis, psi_source):
        notes.append(f"the line found at {1 / found.period:.5g} Hz is a harmonic of the spindle's (as sampled, "
                     "folded at half the sample rate): the spindle period explains it")
        return None
    alt = prob.tuned("locally_periodic", found.period, init, tune=tune, k_extra=1, progress=progress,
                     label=f"locally periodic ψ = {found.period:.6g} s")
    _invalidate(alt, _efficiency_check(alt, ls))
    return alt


def _spindle_harmonic(period: float, trial, psis: list[float], psi_source: str) -> bool:
    """A (folded) harmonic of the spindle's line follows the spindle: the periodic kernel at ψ has it."""
    teeth = int(trial.meta.teeth or 1)
    return psi_source == "spindle" and any(
        sampled_harmonic(period, psi, float(trial.meta.Ts), max_harmonic=max(8, 2 * teeth)) for psi in psis)


def _weigh_alternative(alt: Candidate, candidates: list[Candidate], psi_source: str, spindle_rpm: float | None,
                       notes: list[str]) -> tuple[bool, float | None]:
    """Step 6b: ``(off_spindle, suggested)`` for the candidate at the period found in the data.

    A speed read from the samples or the trial's metadata is a presumption about the disturbance, not the
    user's word: when the data clearly prefer another period (by :data:`SUGGEST_MARGIN` over every
    candidate locked to the spindle; a harmonic of the spindle's line never gets here), the disturbance
    does not follow the spindle (a shaker, a pump, a neighbouring machine) and that period competes like
    any other (``off_spindle``). Otherwise ``alt`` is listed but not eligible, and a period the user gave
    is kept, with the better one named (``suggested``) when it is valid and wins by the margin."""
    locked = max((c for c in candidates if c.kernel in PERIODIC_KINDS or c.kernel == "spindle"),
                 key=lambda c: c.log_evidence)
    margin = alt.log_evidence - locked.log_evidence
    if psi_source == "spindle" and spindle_rpm is None and margin > SUGGEST_MARGIN:
        notes.append(f"the disturbance does not follow the spindle: ψ = {alt.period:.6g} s, found in the data, "
                     f"explains it better than every model locked to the spindle's speed (log evidence "
                     f"{margin:+.1f} over the {locked.label}); that period competes like any other, and the "
                     "tracker runs on time, not on the spindle's angle")
        return True, None
    suggested = None
    if alt.valid and margin > SUGGEST_MARGIN:
        suggested = alt.period
        notes.append(f"the data prefer ψ = {alt.period:.6g} s to the {psi_source} period (log evidence "
                     f"{margin:+.1f} over the {locked.label}); check the period (--period {alt.period:.6g})")
    source = {"given": "--period", "spindle": "the spindle speed"}[psi_source]
    alt.notes.append(f"ψ = {alt.period:.6g} s was found in the data; not a choice, the period comes from {source}")
    alt.eligible = False
    return False, suggested




def _spindle_candidates(prob: _Problem, trial, candidates: list[Candidate], init: dict, notes: list[str], *,
                        tune: bool, progress) -> list[Candidate]:
    """The spindle-phase candidates (issue 11 item 1: the tracker's kernel, eq. S1, in identification)
    when the samples carry the spindle and its speed changes — per revolution (``P = 2π``: a tool with
    runout) and, for a tool with several teeth, per tooth (``P = 2π/teeth``: a pattern that repeats
    with every cutting edge); none at constant speed (there it is the locally periodic candidate at
    ψ = 60/rpm) or without spindle data.

    Started from the best tuned locally periodic candidate (σ1, σ2 mean the same in both kernels);
    the stretches of constant speed are cut with that candidate's σ2
    (:func:`kernels.spindle_phase.segment_tolerance`)."""
    theta = spindle_phase(trial.t, trial.spindle_angle, trial.spindle_rpm)
    if theta is None:
        if trial.spindle_angle is not None or trial.spindle_rpm is not None:
            notes.append("no spindle-phase candidate: the spindle columns have samples without a finite angle or "
                         "speed (the spindle's phase needs every sample's spindle_angle, or spindle_rpm with holes of "
                         f"at most {MAX_HOLE:g} s)")
        return []
    periodic = [c for c in candidates if c.kernel == "locally_periodic" and c.hyperparameters.get("tuned")]
    ref = max(periodic, key=lambda c: c.log_evidence) if periodic else None
    start = dict(init) if ref is None else {k: ref.hyperparameters[k] for k in ("sigma1", "sigma2")} | {"gamma": ref.gamma}
    teeth = int(trial.meta.teeth or 1)
    out = []
    for per, P in (("revolution", 2.0 * math.pi), ("tooth", 2.0 * math.pi / teeth))[: 2 if teeth > 1 else 1]:
        try:
            phase = phase_segments(trial.t[:-1], theta[:-1], segment_tolerance(start["sigma2"], P))
            if phase.count < 2:  # one speed: the locally periodic candidate at 60/rpm is this model
                return out
            cand = prob.tuned("spindle", P, start, tune=tune, k_extra=0, progress=progress, refine=ref is not None,
                              label=f"spindle phase per {per} ({phase.count} stretches of constant speed)", phase=phase)
        except ValueError as exc:
            notes.append(f"no spindle-phase candidate per {per}: {exc}")
            continue
        cand.hyperparameters["per"] = per
        out.append(cand)
    return out


def _harmonic_alternatives(prob: _Problem, cand: Candidate, psi: float, duration: float, progress) -> Candidate:
    """Harmonics considered: a line found at 1/ψ may be a harmonic of a longer true period (e.g. the
    tooth-passing line of a tool with runout). Each multiple ``m ψ`` (m = 2, 3, within the record) is
    evaluated with the hyperparameters carried over (σ1 kept, σ2/m so that the within-period
    smoothness stays the same in seconds); if one beats the tuned ψ it is tuned and evaluated in
    full, and the candidate with the higher evidence is kept."""
    if cand.hyperparameters.get("sigma1") is None:
        return cand
    best = cand
    for m in (2, 3):
        q = m * psi
        if q > min(duration / MIN_CYCLES, MAX_PERIOD_FRACTION * duration):
            break
        s1 = max(cand.hyperparameters["sigma1"], 2.0 * q)
        s2 = max(cand.hyperparameters["sigma2"] / m, 1e-3)
        try:
            ll = prob.terms(LocallyPeriodic(s1, s2, q), cand.gamma).log_likelihood
        except ValueError:
            continue
        if ll > cand.log_likelihood:
            alt = prob.tuned("locally_periodic", q, {"sigma1": s1, "sigma2": s2, "gamma": cand.gamma}, tune=True,
                             k_extra=1, progress=progress, label=f"locally periodic ψ = {q:.6g} s")
            alt.notes.append(f"ψ = {q:.6g} s ({m}× the line found at {psi:.6g} s) explains the residual better")
            if alt.log_evidence > best.log_evidence:
                best = alt
    return best




def _spindle(trial) -> dict | None:
    """``{"teeth", "spindle_rpm"}`` (median speed, rpm) when the samples carry the spindle (then the
    model gets the spindle-phase tracker kernel), else None."""
    rpm = trial.spindle_rpm
    if rpm is None and trial.spindle_angle is not None:
        rpm = np.diff(trial.spindle_angle) / np.diff(trial.t) * 60.0 / (2.0 * math.pi)
    rpm = None if rpm is None else rpm[np.isfinite(rpm)]
    if rpm is None or rpm.size == 0 or not 0.0 < float(np.median(np.abs(rpm))) <= OS.SPINDLE_RPM_MAX:
        return None
    return {"teeth": trial.meta.teeth or 1, "spindle_rpm": float(np.median(np.abs(rpm)))}


