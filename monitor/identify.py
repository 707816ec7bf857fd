"""Offline identification of one axis: candidate models, chosen by evidence among the valid ones
(method §2–5; issue 10).

:func:`identify` takes a :class:`feedio.mcapio.Trial` and returns an :class:`Identification`.

**Regression.** ``z(k)`` of method §2 with the constant column ``one`` in both input forms, and the
friction columns in their identifiable form ``−τ(v), −|τ(v)|`` (the latter only when the trial has
rest, :func:`kernels.feed_drive.rest_samples`; :func:`kernels.feed_drive.friction_transform`),
mapped back to the spec's β for the model file.

**Candidates** (every one on the same ``Z̃``, so their REML are comparable, eq. L2):

* ``ls`` — least squares, ``A = I``;
* ``pl_lssvm`` with a squared-exponential kernel in time (non-periodic disturbances: steps, drift);
* ``pl_lssvm`` with the locally periodic kernel at each period in play (:func:`periods_in_play`), and
  with its zero-mean form (:class:`kernels.covariance.ZeroMeanLocallyPeriodic`, tuned from the former's
  optimum): the locally periodic kernel carries a slowly varying mean (most of its variance when σ2 is
  large), right for a cutting force whose mean follows the feed, wrong for a zero-mean vibration,
  where that mean competes with the velocity column; the evidence tells which one the data support;
* ``pl_lssvm`` with the spindle-phase kernel (the tracker's, on ``(t, θ)``) when the samples carry the
  spindle and its speed changes (:func:`_spindle_candidates`: per revolution and per tooth,
  block-diagonal over the stretches of constant speed, :mod:`kernels.spindle_phase`).

**Period.** In this order: ``period`` ("given"), the spindle speed ("spindle"), else found in the LS
residual ("detected", :func:`kernels.period.detect_periods`: harmonic-sum periodogram, periods locked
to the commanded motion left out, at least ``MIN_CYCLES`` periods in the record) — then the
multiples 2ψ and 3ψ are tried on the likelihood (:func:`_harmonic_alternatives`: a line found at
1/ψ may be a harmonic of a longer true period) — else none. A period found in the data counts as one
more fitted hyperparameter. With a given (or spindle) period the detected one is tuned too. When it is
valid and its evidence exceeds the best candidate at the given period (or on the spindle's phase) by
``SUGGEST_MARGIN``, the output says so and names it (``period_suggested``), but a period the user gave
(``period``, ``spindle_rpm``) is kept. A spindle speed read from the samples or the trial's
metadata is only a presumption: when the detected period beats every spindle-locked candidate by that
margin, the disturbance does not follow the spindle, the detected period competes like any other
(source "detected") and the tracker runs on time, not on the spindle's angle.

Each kernel candidate is tuned by the REML (:func:`kernels.likelihood.tune`; ``tune=False`` keeps the
given or thesis hyperparameters), then evaluated exactly: REML ``ℓ``, GLS covariance of β (eq. L3),
physical parameters and their standard errors by the delta method, and the evidence
``log E = ℓ − ½ k log(N − p)`` (eq. L4, ``k`` tuned hyperparameters, +1 for a period found in the data).

**Validity.** A candidate is not a valid choice when

1. :func:`kernels.feed_drive.validity_problems` finds a reason it cannot be right (pole outside
   (0, 1), input gain ≤ 0, a Coulomb friction negative beyond ``COULOMB_Z`` standard errors); or
2. (kernel candidates) it determines the inertia or the symmetric Coulomb friction
   (``EFFICIENCY_KEYS``, or their ratios to the loop gain) *worse than least squares does*: its GLS
   standard error exceeds the LS standard error. The GLS covariance ``ŝ²(Z̃ᵀA⁻¹Z̃)⁻¹`` grows where
   the kernel can reproduce a regressor column — a flexible kernel in time can draw ``sign(v)`` or
   the acceleration transients — and shrinks where it removes a disturbance that LS mistakes for
   noise. A disturbance model that explains the residual but costs precision on these parameters
   competes with them (on clean real data, where the equation error is coloured by filtering and
   unmodelled dynamics, a kernel otherwise takes the Coulomb friction): the trial does not
   determine them under that candidate. Damping is not part of the rule: its column, the velocity,
   varies as slowly as any disturbance a time kernel admits (the squared exponential, and the
   slowly drifting mean of the locally periodic kernel), so every disturbance model competes with
   it to some degree — in milling the mean cutting force even follows the feed; this is reported
   instead (below); or
3. a candidate that explains the data far better (log evidence higher by more than
   ``SUGGEST_MARGIN``) and determines the parameters at least as well as LS (rule 2 holds for it;
   rule 1 need not: a model that cannot be right still shows that the parameters move with the
   disturbance model) puts the inertia or the symmetric Coulomb friction
   (``EFFICIENCY_KEYS``) more than ``BIAS_Z`` combined standard errors *and* ``BIAS_SHARE`` (3 %) away
   from this one's
   (:func:`_bias_check`, a Hausman-type comparison; the combined error ``√(se₁² + se₂²)`` is the
   larger, cautious one). The standard errors of a candidate hold *if its disturbance model is
   right*; when the data reject that model by such a margin and the parameters move with the
   model, they are the disturbance's, not the drive's. Measured: milling with the spindle at
   300 rpm (5 Hz, inside the feed's band), J = 1500 kg: LS gave 27 953 ± 4 501 kg and was chosen,
   the periodic candidates (+11 768 in evidence, negative Coulomb friction) 8 738 ± 431 kg —
   4.2 s.e. apart: now no candidate is valid and the model is refused. On ``DATA_EMPS`` the kernel
   candidates win by ~5 000 and move the Coulomb friction from 20.3 to 5–8 N, but they determine it
   worse than LS (rule 2): they are no witnesses, LS stays the model.

**Choice.** The valid candidate with the highest evidence (``method="auto"``); ``method="ls"`` or
``"pl-lssvm"`` restricts the choice to that family. No valid candidate: ``refusal`` says why (the
command exits 1 and writes nothing unless ``--force``).

**Uncertainty flags.** A physical parameter whose relative standard error exceeds
``UNDETERMINED_RSE`` is reported as "not determined (± s.e.)", never as a fact. A parameter whose
variance the disturbance model inflates by more than ``VIF_FLAG`` —
``VIF = var_GLS(φ) / var_white(φ)``, the delta-method variance of φ under the candidate over its
variance with the same noise level ``ŝ²/γ`` and no disturbance model, ``(ŝ²/γ)(Z̃ᵀZ̃)⁻¹`` — is
flagged as *competing with the disturbance model*: it is determined only on the assumption that the
disturbance has no component that follows that regressor (``1/VIF`` of the column's information
is left to determine it).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from feedio.limits import PHYSICAL
from kernels import LocallyPeriodic, SquaredExponential
from kernels.errors import ParameterError
from kernels.feed_drive import (
    COULOMB_Z,
    beta_to_physical,
    disturbance_to_force,
    friction_transform,
    physical_covariance,
    physical_to_beta,
    regressors,
    rest_samples,
    simulate_free_run,
    validity_problems,
)
from kernels.likelihood import PERIODIC_KINDS, _make_kernel, log_evidence, reml_terms
from kernels.likelihood import tune as tune_hyperparameters
from kernels.low_speed import LowSpeedFriction, low_speed_friction
from kernels.period import MIN_CYCLES, detect_periods, harmonically_related, sampled_harmonic
from kernels.pl_lssvm import LEVINSON_LIMIT, pl_lssvm, prepare_regression
from kernels.spindle_phase import MAX_HOLE, phase_segments, segment_tolerance, spindle_phase

from . import online_settings as OS
from .model_file import OMEGA_MAX, AxisModel, TrackerConfig, file_sha256

__all__ = ["THESIS_DEFAULTS", "TRACKER_DEFAULTS", "MAX_SAMPLES", "too_long", "UNDETERMINED_RSE", "EFFICIENCY_KEYS", "VIF_FLAG", "SUGGEST_MARGIN",
           "COULOMB_Z", "Identification", "Candidate", "MethodResult", "identify", "periods_in_play", "dead_band"]

#: PL-LSSVM hyperparameters when neither given nor tuned (thesis Table 4.1, case study 1)
THESIS_DEFAULTS = {"sigma1": 0.59, "sigma2": 0.42, "gamma": 50.3}
#: online KRLS-T defaults (one definition: monitor.online_settings)
TRACKER_DEFAULTS = OS.TRACKER_DEFAULTS
#: samples needed beyond ±Ω on each side before the Coulomb columns are identifiable
MIN_REVERSAL_SAMPLES = 20
#: samples at rest needed before the Coulomb asymmetry is told from the offset
MIN_REST_SAMPLES = 20
#: relative standard error above which a physical parameter is "not determined"
UNDETERMINED_RSE = 0.25
#: parameters a kernel candidate must determine at least as well as LS (validity rule 2)
EFFICIENCY_KEYS = ("inertia", "coulomb")
#: variance inflation above which a parameter is flagged as competing with the disturbance model
VIF_FLAG = 10.0
#: log-evidence margin by which another period must beat a given one to be suggested (and by which a
#: better-explaining candidate must win to test another's parameters for bias, validity rule 3)
SUGGEST_MARGIN = 10.0
#: combined standard errors by which a far better-explaining candidate's parameters may differ (rule 3) …
BIAS_Z = 3.0
#: … and the share of its value (as the health drift test's 3 %: a statistically clear but small bias,
#: LS 1493 ± 2 kg against 1501 ± 0.6 kg for a 1500 kg drive, is no reason to refuse a model)
BIAS_SHARE = 0.03
#: share of the samples a spindle speed must hold to put its period in play
SPINDLE_SHARE = 0.1
#: longest period relative to the record (the kernel needs σ1 ≥ 2ψ)
MAX_PERIOD_FRACTION = 0.5
#: most samples one identification takes: the exact REML of a kernel candidate costs O(N²) per
#: evaluation (Levinson), ~2.5 min for all candidates at 40 000 samples, ~6 min at this limit;
#: a longer record is refused with the fix (a window: ``--start``/``--end``)
MAX_SAMPLES = 60_000

_METHOD_LABEL = {"ls": "LS", "pl_lssvm": "PL-LSSVM"}


def dead_band(v_meas: np.ndarray) -> float:
    """Coulomb dead band Ω (m/s): the larger of 3× the velocity noise and 0.5 % of the peak speed.

    The noise is estimated from second differences, ``σ ≈ 1.4826·MAD(Δ²v)/√6`` (white
    noise: Var Δ²v = 6σ²). The floor of 0.5 % of max|v| keeps samples at rest inside the
    band when the velocity is a smooth filtered derivative (EMPS), where the noise
    estimate is tiny and no sample would otherwise count as standing still.
    """
    v = np.asarray(v_meas, dtype=np.float64)
    d2 = np.diff(v, 2)
    if d2.size == 0:
        return 0.0
    mad = float(np.median(np.abs(d2 - np.median(d2))))
    return max(3.0 * 1.4826 * mad / math.sqrt(6.0), 0.005 * float(np.max(np.abs(v))))


# ------------------------------------------------------------------------------------------------
# periods
# ------------------------------------------------------------------------------------------------
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


# ------------------------------------------------------------------------------------------------
# candidates
# ------------------------------------------------------------------------------------------------
@dataclass
class Candidate:
    """One candidate model, evaluated exactly on the whole record."""

    method: str  # "ls" | "pl_lssvm"
    kernel: str | None  # None | "squared_exponential" | "locally_periodic" | "locally_periodic_zero_mean" | "spindle"
    period: float | None
    hyperparameters: dict  # sigma1, sigma2 | lengthscale, gamma (+ tuned, evaluations, on_bound)
    k: int  # hyperparameters fitted to the data (eq. L4)
    log_likelihood: float
    log_evidence: float
    beta: np.ndarray  # spec β (model-file order)
    beta_cov: np.ndarray
    physical: dict
    physical_se: dict
    pole: float
    valid: bool = True
    why_not: str | None = None
    notes: list[str] = field(default_factory=list)
    kernel_object: object = None
    gamma: float | None = None
    vif: dict = field(default_factory=dict)  # variance inflation of each physical parameter by the kernel
    eligible: bool = True  # False: evaluated for the period check only (the period was given)
    phase: object = None  # kernels.spindle_phase.PhaseSegments of the spindle-phase candidate

    @property
    def label(self) -> str:
        if self.method == "ls":
            return "LS"
        if self.kernel == "locally_periodic":
            return f"PL-LSSVM, locally periodic ψ = {self.period:.6g} s"
        if self.kernel == "locally_periodic_zero_mean":
            return f"PL-LSSVM, zero-mean locally periodic ψ = {self.period:.6g} s"
        if self.kernel == "spindle":
            return f"PL-LSSVM, spindle phase per {self.hyperparameters.get('per', 'revolution')}"
        return "PL-LSSVM, squared exponential"

    @property
    def beta_se(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.beta_cov), 0.0))

    def summary(self) -> dict:
        """The ``candidates`` entry of the JSON document."""
        return {"method": self.method, "kernel": self.kernel, "period": self.period,
                "hyperparameters": self.hyperparameters, "log_evidence": self.log_evidence,
                "valid": self.valid, "why_not": self.why_not}


@dataclass
class MethodResult:
    """A fitted candidate with its predictions (the ``ls`` / ``pl_lssvm`` sections)."""

    name: str
    candidate: Candidate
    rmse_linear: float  # y − Zβ (m/s)
    rmse: float  # one-step prediction error (m/s), with the disturbance for PL-LSSVM
    rmse_free_run: float  # free-run simulation error (m/s)
    prediction: np.ndarray  # one-step velocity prediction aligned with y
    f: np.ndarray | None = None  # disturbance estimate (m/s) aligned with y
    f_force: np.ndarray | None = None  # the same in N when scalable

    @property
    def beta(self) -> np.ndarray:
        return self.candidate.beta

    @property
    def stderr(self) -> np.ndarray:
        return self.candidate.beta_se

    @property
    def physical(self) -> dict:
        return self.candidate.physical

    @property
    def physical_se(self) -> dict:
        return self.candidate.physical_se

    def undetermined(self) -> list[str]:
        """Physical parameters whose relative standard error exceeds ``UNDETERMINED_RSE``."""
        return undetermined(self.physical, self.physical_se)

    def competing(self) -> list[str]:
        """Physical parameters whose variance the disturbance model inflates by more than ``VIF_FLAG``."""
        return [k for k, v in self.candidate.vif.items() if v > VIF_FLAG]

    def to_json(self, names, notes) -> dict:
        c = self.candidate
        return {"method": c.method, "kernel": c.kernel, "period": c.period, "beta_names": list(names),
                "beta": c.beta.tolist(), "beta_se": c.beta_se.tolist(), "physical": c.physical,
                "physical_se": {k: v for k, v in c.physical_se.items() if not k.startswith("_")},
                "undetermined": self.undetermined(), "competing": self.competing(), "vif": c.vif,
                "pole": c.pole, "hyperparameters": c.hyperparameters,
                "log_likelihood": c.log_likelihood, "log_evidence": c.log_evidence, "valid": c.valid,
                "why_not": c.why_not, "rmse": self.rmse, "rmse_linear": self.rmse_linear,
                "rmse_free_run": self.rmse_free_run, "notes": list(notes) + c.notes}


def undetermined(physical: dict, physical_se: dict) -> list[str]:
    """Keys of ``physical`` with ``s.e. > UNDETERMINED_RSE · |value|``."""
    out = []
    for k, v in physical.items():
        s = physical_se.get(k)
        if s is not None and not (s <= UNDETERMINED_RSE * abs(v)):
            out.append(k)
    return out


@dataclass
class Identification:
    """Everything ``feedmon identify`` found on one axis of a trial."""

    trial_path: str
    machine: str
    axis: str
    form: str
    Ts: float
    period: float | None  # ψ of the periodic candidate(s) in play (the chosen one's when periodic)
    period_source: str  # given | spindle | detected | none
    period_suggested: float | None
    omega: float
    coulomb: bool
    coulomb_note: str
    rest: bool
    names: tuple[str, ...]  # spec β names (model file)
    loop_gain: float | None
    candidates: list[Candidate]
    chosen: Candidate | None
    ls: MethodResult
    pl: MethodResult | None
    model_result: MethodResult | None
    y: np.ndarray  # v_m(k+1), m/s
    t: np.ndarray  # time of y (s)
    refusal: str | None = None
    truth: dict | None = None
    truth_force: np.ndarray | None = None  # true disturbance force (N) aligned with y
    truth_f: np.ndarray | None = None  # true disturbance (m/s) aligned with y
    measured_force: np.ndarray | None = None  # e.g. dynamometer (N) aligned with y
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def chosen_method(self) -> str | None:
        return None if self.chosen is None else self.chosen.method

    @property
    def f(self) -> np.ndarray | None:
        """Disturbance estimate of the PL-LSSVM result (m/s)."""
        return None if self.pl is None else self.pl.f

    @property
    def f_force(self) -> np.ndarray | None:
        return None if self.pl is None else self.pl.f_force

    @property
    def hyperparameters(self) -> dict:
        return {} if self.pl is None else self.pl.candidate.hyperparameters
    spindle: dict | None = None  # {"teeth", "spindle_rpm"} when the trial's samples carry spindle data
    periods: list[float] = field(default_factory=list)  # every ψ in play (s; several when the spindle speed changes)
    low_speed: LowSpeedFriction | None = None  # the friction law near standstill (kernels.low_speed)

    def to_json(self) -> dict:
        """The ``--json`` document (issue 10): exactly the keys form, Ts, chosen, period, candidates,
        ls, pl_lssvm, model, truth."""
        model = None
        if self.model_result is not None:
            c = self.model_result.candidate
            model = {"method": c.method, "beta": c.beta.tolist(), "beta_se": c.beta_se.tolist(),
                     "physical": c.physical,
                     "physical_se": {k: v for k, v in c.physical_se.items() if not k.startswith("_")}}
        return {
            "form": self.form,
            "Ts": self.Ts,
            "chosen": self.chosen_method,
            "period": {"value": self.period, "source": self.period_source, "suggested": self.period_suggested},
            "candidates": [c.summary() for c in self.candidates],
            "ls": self.ls.to_json(self.names, self.notes),
            "pl_lssvm": None if self.pl is None else self.pl.to_json(self.names, self.notes),
            "model": model,
            "truth": self.truth,
        }

    def _tracker_kernel(self, chosen, psi) -> tuple[str, dict | None]:
        """The online tracker's kernel family and σ1, σ2, γ (issue 11: REML-tuned values track best).

        The tracker follows the evidence: the chosen candidate's kernel when it is a locally periodic one
        at the tracker's period ψ (its zero-mean form too — a disturbance without a slowly varying mean,
        so the tracker leaves slow forces to β, online as offline); when the chosen model is LS or of
        another kernel, the best tuned locally periodic candidate at ψ by evidence. ``("locally_periodic",
        None)`` (thesis values) when none was tuned. With spindle data the tracker runs the spindle-phase
        kernel: the tuned spindle-phase candidate's values when there is one (the speed changed)."""
        if self.spindle:
            spindle = [c for c in self.candidates if c.kernel == "spindle" and c.hyperparameters.get("tuned")]
            if spindle:
                return "spindle", max(spindle, key=lambda c: c.log_evidence).hyperparameters
        families = ("locally_periodic", "locally_periodic_zero_mean")
        if psi is not None:
            others = sorted((x for x in self.candidates if x is not chosen),
                            key=lambda x: -(x.log_evidence if x.log_evidence is not None else -math.inf))
            for cand in [chosen, *others]:
                hp = cand.hyperparameters
                if (cand.kernel in families and cand.period is not None
                        and abs(cand.period - psi) <= 1e-9 * psi and hp.get("tuned")
                        and all(hp.get(k) is not None for k in ("sigma1", "sigma2", "gamma"))):
                    return cand.kernel, hp
        return "locally_periodic", None

    def to_model(self, *, tracker: dict | None = None, feedmon_version: str = "", force: bool = False) -> AxisModel:
        """The axis model file for ``feedmon run``: β of the chosen candidate (of the best one by
        evidence when ``force`` and nothing is valid), the tracker defaults with ψ = the period."""
        res = self.model_result
        if res is None:
            raise ValueError(self.refusal or "no model to write")
        c = res.candidate
        if not c.valid and not force:
            raise ValueError(f"the {c.label} model is not valid: {c.why_not}")
        # the tracker's period: the chosen model's, else one the user gave (a period found in the data
        # whose candidates were not chosen is no reason to make the online kernel periodic)
        psi = c.period if c.period is not None else (self.period if self.period_source in ("given", "spindle") else None)
        family, tuned = self._tracker_kernel(c, psi)
        # issue 11: λ, M from measurements, σ1, σ2, γ from REML when tuned, the spindle-phase kernel when
        # the samples carry the spindle (monitor.online_settings.tracker_table, one definition)
        spindle = self.spindle if family != "spindle" else {**self.spindle, "per": tuned.get("per", "revolution")}
        cfg = OS.tracker_table(tuned=tuned, period=psi or 1.0, spindle=spindle)
        if psi is None and not self.spindle:  # no periodic disturbance in play: a smooth, slowly varying one
            cfg["kernel"] = SquaredExponential(cfg["kernel"]["sigma1"]).to_dict()
        elif not self.spindle and family != "locally_periodic":
            cfg["kernel"] = {**cfg["kernel"], "type": family}
        for key, value in (tracker or {}).items():  # explicit settings: kernel hyperparameters go into the kernel
            if key in cfg["kernel"] and key != "type":
                cfg["kernel"] = {**cfg["kernel"], key: value}
            else:
                cfg[key] = value
        kernel = cfg["kernel"]
        ident = {"chosen": c.method, "kernel": c.kernel or "none", "period": c.period,
                 "period_source": self.period_source, "log_evidence": c.log_evidence}
        ident.update({k: v for k, v in c.hyperparameters.items() if isinstance(v, (int, float, bool))})
        candidates = [{"method": x.method, "kernel": x.kernel or "none", "period": x.period,
                       "log_evidence": x.log_evidence, "valid": x.valid, "why_not": x.why_not or ""}
                      | ({"per": x.hyperparameters.get("per", "revolution")} if x.kernel == "spindle" else {})
                      for x in self.candidates]
        warning = None if c.valid else f"written with --force although invalid: {c.why_not}"
        return AxisModel(
            machine=self.machine,
            axis=self.axis,
            form=self.form,
            Ts=self.Ts,
            beta=[float(b) for b in c.beta],
            beta_names=tuple(self.names),
            beta_se=[float(s) for s in c.beta_se],
            omega=self.omega,
            coulomb=self.coulomb,
            loop_gain=self.loop_gain,
            method="ls" if c.method == "ls" else "pl-lssvm",
            tracker=TrackerConfig(kernel=kernel, gamma=cfg["gamma"], forgetting=cfg["forgetting"],
                                  budget=int(cfg["budget"]), jitter=cfg["jitter"]),
            physical=dict(c.physical),
            physical_se={k: v for k, v in c.physical_se.items() if not k.startswith("_")},
            identification=ident,
            candidates=candidates,
            validity_warning=warning,
            # β learns only where the friction law holds (kernels.low_speed); every other setting its default
            online=OS.OnlineSettings(adaptation=OS.Adaptation(
                min_speed=float(self.low_speed.min_speed) if self.low_speed is not None else 0.0)),
            provenance={
                "source": self.trial_path,
                "sha256": file_sha256(self.trial_path),
                "method": "ls" if c.method == "ls" else "pl-lssvm",
                "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
                "feedmon_version": feedmon_version,
            },
        )


def _rmse(a: np.ndarray) -> float:
    return float(math.sqrt(np.mean(a * a)))


_BOUND_MEANING = {
    ("sigma1", "lower"): "the periodic pattern changes from one period to the next (barely periodic at this ψ)",
    ("sigma1", "upper"): "the periodic pattern keeps its shape over the whole tuning window (a stationary "
                         "periodic disturbance); longer correlation cannot be told apart",
    ("sigma2", "lower"): "the pattern has sharper features (edges, impacts) than the kernel can follow; "
                         "finer detail is smoothed",
    ("sigma2", "upper"): "the pattern is close to a pure sine at 1/ψ",
    ("lengthscale", "lower"): "the disturbance varies as fast as the kernel allows (it may be modelling "
                              "coloured noise rather than a disturbance)",
    ("lengthscale", "upper"): "the disturbance is nearly constant over the tuning window (a slow drift or offset)",
    ("gamma", "lower"): "the disturbance is weaker than the noise: this model adds next to nothing",
    ("gamma", "upper"): "the kernel explains nearly all of the residual (noise at its floor); it may be "
                        "absorbing model error as well as a disturbance",
}


class _Abandoned(Exception):
    """Raised in a tuning thread whose result is no longer wanted (the identification failed)."""


class _TunedBeside:
    """:meth:`_Problem.tuned` on a second thread while this one tunes other candidates (the likelihood's
    Levinson pass releases the interpreter lock: ~1.45× on 2 cores for EMPS at 1 kHz). Leaving the
    ``with`` block by an exception stops it after its current evaluation (its progress callback raises
    :class:`_Abandoned`); leaving it in any way joins the thread."""

    def __init__(self, prob: _Problem, *args, progress=None, **kwargs) -> None:
        self._stop = threading.Event()
        self._progress = progress
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="identify-beside")
        self._future = self._pool.submit(prob.tuned, *args, progress=self._report, **kwargs)

    def _report(self, *args) -> None:
        if self._stop.is_set():
            raise _Abandoned
        if self._progress is not None:
            self._progress(*args)

    def result(self) -> Candidate:
        return self._future.result()

    def __enter__(self) -> _TunedBeside:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is not None:
            self._stop.set()
        self._pool.shutdown(wait=True)


class _Problem:
    """The regression of one trial shared by all candidates."""

    def __init__(self, form, Ts, gain, names, T, Z_id, id_names, y, exo, v, omega, coulomb):
        self.form, self.Ts, self.gain, self.names, self.T = form, Ts, gain, names, T
        self.Z, self.id_names, self.y, self.exo, self.v = Z_id, id_names, y, exo, v
        self.omega, self.coulomb = omega, coulomb
        self.prepared = prepare_regression(Z_id, y, id_names)
        self.n, self.p = Z_id.shape

    def candidate(self, method, kernel_kind, kernel, gamma, hyper, k, notes=(), terms=None, phase=None) -> Candidate:
        if terms is None:
            terms = reml_terms(None, None, kernel, gamma, self.Ts, phase=phase, _prepared=self.prepared)
        beta = self.T @ terms.beta
        cov = self.T @ terms.beta_cov @ self.T.T
        try:
            phys, se = physical_covariance(self.form, beta, cov, self.Ts, gain=self.gain, names=self.names)
            pole = beta_to_physical(self.form, beta, self.Ts, gain=self.gain, names=self.names).pole
        except ValueError:
            phys, se = {}, {}
            pole = float(beta[0] + beta[1]) if self.form == "velocity-loop" else float(beta[1])
        problems = validity_problems(self.form, beta, self.Ts, names=self.names, gain=self.gain,
                                     physical_se={k_: v for k_, v in se.items() if not k_.startswith("_")})
        vif = {}
        if kernel is not None and phys:
            Zt = self.prepared[3]
            white = self.T @ ((terms.s2 / gamma) * np.linalg.pinv(Zt.T @ Zt)) @ self.T.T
            _, se_white = physical_covariance(self.form, beta, white, self.Ts, gain=self.gain, names=self.names)
            vif = {k_: (se[k_] / se_white[k_]) ** 2 for k_ in phys if se_white.get(k_, 0.0) > 0.0}
        cand = Candidate(method=method, kernel=kernel_kind, period=getattr(kernel, "period", None),
                         hyperparameters=hyper, k=k, log_likelihood=terms.log_likelihood,
                         log_evidence=log_evidence(terms.log_likelihood, k, self.n, self.p), beta=beta,
                         beta_cov=cov, physical=phys, physical_se=se, pole=pole, notes=list(notes),
                         kernel_object=kernel, gamma=gamma, vif=vif, phase=phase)
        if problems:
            cand.valid, cand.why_not = False, "; ".join(problems)
        return cand

    def tuned(self, kind, period, init, tune, k_extra, progress, label, refine: bool = False, phase=None) -> Candidate:
        """A kernel candidate: tuned by REML (or the given/thesis values), then evaluated exactly
        (block-diagonally on the stretches ``phase`` for the spindle-phase kernel).
        ``refine``: ``init`` is a good start (the optimum of a related family): no start design, fewer
        evaluations."""
        notes = []
        if tune:
            res = tune_hyperparameters(None, None, self.Ts, period, kind=kind, init=init, _prepared=self.prepared,
                                       progress=None if progress is None else (lambda *a: progress(label, *a)),
                                       design=not refine, max_evaluations=20 if refine else 30, phase=phase)
            hyper = dict(res.hyper, gamma=res.gamma, tuned=True, evaluations=res.evaluations,
                         tune_seconds=round(res.seconds, 3))
            if res.on_bound:
                hyper["on_bound"] = dict(res.on_bound)
            for name, side in res.on_bound.items():
                lo, hi = res.bounds[name]
                notes.append(f"{label}: {name} ended on its {side} bound ({lo if side == 'lower' else hi:.4g}): "
                             f"{_BOUND_MEANING[(name, side)]}")
            kernel, gamma, terms = res.kernel(), res.gamma, res.terms
            k = len(res.hyper) + 1 + k_extra
        else:
            if kind in PERIODIC_KINDS or kind == "spindle":
                values = {"sigma1": init["sigma1"], "sigma2": init["sigma2"]}
            else:
                values = {"lengthscale": init["lengthscale"]}
            kernel = _make_kernel(kind, values, period)
            hyper = dict(values, gamma=init["gamma"], tuned=False)
            gamma, terms = init["gamma"], None
            k = k_extra
        if kind == "locally_periodic_zero_mean":
            notes.append(f"{label}: the disturbance is taken to have zero mean, so the offset also holds the "
                         "disturbance's mean force (the two cannot be told apart)")
        return self.candidate("pl_lssvm", kind, kernel, gamma, hyper, k, notes, terms, phase)

    def fit(self, cand: Candidate, trial_exo_name) -> MethodResult:
        """Predictions (and, for PL-LSSVM, the disturbance estimate) of a candidate."""
        theta = np.linalg.lstsq(self.T, cand.beta, rcond=None)[0]
        linear = self.Z @ theta
        f = None
        if cand.method == "pl_lssvm":
            solver = "levinson" if self.n <= LEVINSON_LIMIT else "auto"
            res = pl_lssvm(self.Z, self.y, cand.kernel_object, cand.gamma, Ts=self.Ts, names=self.id_names,
                           solver=solver, phase=cand.phase)
            f = res.f
            linear = self.Z @ res.beta
        pred = linear + (f if f is not None else 0.0)
        with np.errstate(over="ignore", invalid="ignore"):  # an invalid (unstable) model diverges
            sim = simulate_free_run(self.form, cand.beta, self.v[0], self.exo, omega=self.omega,
                                    coulomb=self.coulomb, disturbance=None if f is None else np.append(f, 0.0),
                                    intercept=True)
            err = sim - self.v
            free = _rmse(err) if np.all(np.isfinite(err)) else math.inf
        f_force = None
        scalable = self.form == "force-input" or self.gain is not None
        if f is not None and scalable and cand.beta[0] > 0:
            f_force = disturbance_to_force(self.form, cand.beta, f, gain=self.gain)
        return MethodResult(name=_METHOD_LABEL[cand.method], candidate=cand, rmse_linear=_rmse(self.y - linear),
                            rmse=_rmse(self.y - pred), rmse_free_run=free, prediction=pred, f=f, f_force=f_force)


def _efficiency_check(cand: Candidate, ls: Candidate) -> str | None:
    """Validity rule 2 (module docstring): None, or why the candidate determines β worse than LS."""
    worse = []
    for key in EFFICIENCY_KEYS:
        for name in (key, f"{key}_over_gain"):
            a, b = cand.physical_se.get(name), ls.physical_se.get(name)
            if a is None or b is None:
                continue
            if a > b:
                worse.append(f"{name} ± {a:.3g} vs ± {b:.3g}")
    if not worse:
        return None
    return ("the disturbance model competes with the drive's regressors: it determines "
            + ", ".join(worse) + " (LS) — worse than least squares, so this trial does not separate its "
            "disturbance from the drive's parameters")


def _bias_check(cand: Candidate, witnesses: list[Candidate]) -> str | None:
    """Validity rule 3 (module docstring): None, or why one of ``witnesses`` (candidates that determine
    the parameters at least as well as LS: rule 2 holds for them) explains the data far better and shows
    ``cand``'s parameters to be biased by the disturbance it leaves out."""
    for other in witnesses:
        margin = other.log_evidence - cand.log_evidence
        if other is cand or not margin > SUGGEST_MARGIN:
            continue
        for key in EFFICIENCY_KEYS:
            for name in (key, f"{key}_over_gain"):
                a, b = cand.physical.get(name), other.physical.get(name)
                sa, sb = cand.physical_se.get(name), other.physical_se.get(name)
                if None in (a, b, sa, sb) or not all(map(math.isfinite, (a, b, sa, sb))):
                    continue
                z = abs(a - b) / math.hypot(sa, sb) if sa > 0 or sb > 0 else math.inf
                if z > BIAS_Z and abs(a - b) > BIAS_SHARE * abs(b):
                    return (f"biased by the disturbance it leaves out: {other.label} explains the data far better "
                            f"(log evidence {margin:+.0f}) and puts {name} at {b:.4g} ± {sb:.2g}, {z:.1f} s.e. from "
                            f"this model's {a:.4g} ± {sa:.2g}")
    return None


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
    progress=None,
) -> Identification:
    """Identify one axis: candidates, evidence, validity, choice (module docstring).

    ``coulomb=None`` keeps the Coulomb columns when the trial reverses direction (at least
    :data:`MIN_REVERSAL_SAMPLES` samples beyond ±Ω each way) and drops them otherwise, with a
    note; ``coulomb=True`` insists (and fails on a trial without reversal with the kernels' rank
    error). ``omega=None`` estimates the dead band with :func:`dead_band`. ``method``: "auto",
    "ls" or "pl-lssvm". ``progress(label, evaluations, values, ll, best)`` is called while tuning.
    A bad argument raises :class:`~kernels.errors.ParameterError` naming it (``feedmon identify`` adds
    the flag, :mod:`feedmon.errors`).

    The steps, in order (each one function below):

    1. the signals, checked (:func:`_signals`), and the periods in play (:func:`periods_in_play`);
    2. the friction columns: dead band Ω, Coulomb kept or dropped, rest or not (:func:`_friction_columns`);
    3. the regression shared by all candidates and its LS candidate (:class:`_Problem`);
    4. the periods to tune at: given, the spindle's, else found in the LS residual (:func:`_periods_to_try`);
    5. the kernel candidates, tuned by REML (:func:`_kernel_candidates`, :func:`_spindle_candidates`);
    6. with a given or spindle period, the period found in the data, tuned and weighed against it
       (:func:`_detected_alternative`, :func:`_weigh_alternative`);
    7. validity rules 2 and 3 (:func:`_efficiency_check`, :func:`_bias_check`), the choice
       (:func:`_choose`), the fits and the low-speed check (:func:`_low_speed_check`).
    """
    started = time.perf_counter()
    form, exo, exo_name = _signals(trial, form, method)
    Ts, v = float(trial.meta.Ts), trial.v_meas
    psis, psi_source = periods_in_play(trial, period, spindle_rpm)
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
    notes: list[str] = []
    _note_unused_spindle(trial, period, spindle_rpm, psi_source, notes)
    omega_used, coulomb_used, coulomb_note, rest = _friction_columns(v, Ts, omega, coulomb, notes)

    reg = regressors(form, v, v_ref=trial.v_ref if form == "velocity-loop" else None,
                     u=trial.u if form == "force-input" else None, omega=omega_used, coulomb=coulomb_used,
                     intercept=True)
    T, id_names = friction_transform(reg.names, rest)
    prob = _Problem(form, Ts, gain, reg.names, T, reg.Z @ T, id_names, reg.y, exo, v, omega_used, coulomb_used)
    duration = prob.n * Ts
    ls_c = prob.candidate("ls", None, None, None, {}, 0)
    init = {"sigma1": sigma1 or THESIS_DEFAULTS["sigma1"], "sigma2": sigma2 or THESIS_DEFAULTS["sigma2"],
            "gamma": gamma or THESIS_DEFAULTS["gamma"]}
    se_init = {"lengthscale": sigma1, "gamma": gamma} if sigma1 or gamma else None

    psis, psi_source, k_period, detected = _periods_to_try(trial, reg.y - reg.Z @ ls_c.beta, Ts, duration,
                                                           psis, psi_source, notes)
    tuned_kw = dict(tune=tune, progress=progress)
    kernel_candidates, psis = _kernel_candidates(prob, psis, psi_source, k_period, init, se_init, duration,
                                                 notes, **tuned_kw)
    candidates = [ls_c, *kernel_candidates]
    alt = _detected_alternative(prob, psis, psi_source, detected, init, ls_c, **tuned_kw)
    candidates += _spindle_candidates(prob, trial, candidates, init, notes, **tuned_kw)
    off_spindle, suggested, unused = False, None, []
    if alt is not None:
        off_spindle, suggested = _weigh_alternative(alt, candidates, trial, psis, psi_source, spindle_rpm, notes)
        if off_spindle:
            psi_source, psis = "detected", [alt.period]
        else:
            unused.append(alt)

    for c in candidates[1:]:  # validity rule 2: determined at least as well as LS
        _invalidate(c, _efficiency_check(c, ls_c))
    if off_spindle:  # checked in _detected_alternative, with its own evidence of being in play
        candidates.append(alt)
    eligible = [c for c in candidates if c.eligible]
    witnesses = [c for c in eligible if c is ls_c or _efficiency_check(c, ls_c) is None]
    for c, why in [(c, _bias_check(c, witnesses)) for c in eligible]:  # validity rule 3
        _invalidate(c, why)
    chosen, refusal, pl_best, written = _choose(candidates, method)

    ls_res = prob.fit(ls_c, exo_name)
    pl_res = prob.fit(pl_best, exo_name) if pl_best is not None else None
    model_res = None
    if written is ls_c:
        model_res = ls_res
    elif written is pl_best:
        model_res = pl_res
    elif written is not None:
        model_res = prob.fit(written, exo_name)
    low_speed = _low_speed_check(prob, model_res, notes)

    periodic = written if written is not None and written.kernel in PERIODIC_KINDS else None
    psi_report = periodic.period if periodic is not None else (psis[0] if psis else None)
    if gain is None and form == "velocity-loop":
        notes.append("loop gain K unknown: only J/K, B/K and the friction over K are identifiable "
                     "(give --loop-gain to get J and B)")
    ident = Identification(
        trial_path=str(trial.path), machine=trial.machine, axis=trial.axis, form=form, Ts=Ts, period=psi_report,
        period_source=psi_source, period_suggested=suggested, omega=omega_used, coulomb=coulomb_used,
        coulomb_note=coulomb_note, rest=rest, names=reg.names, loop_gain=gain, candidates=candidates + unused,
        chosen=chosen, ls=ls_res, pl=pl_res, model_result=model_res, y=reg.y, t=trial.t[1:], refusal=refusal,
        notes=notes,
    )
    ident.spindle = None if off_spindle else _spindle(trial)
    ident.periods = [float(p) for p in psis]
    ident.low_speed = low_speed
    _attach_truth(ident, trial)
    ident.seconds = time.perf_counter() - started
    return ident


def too_long(path, count: str, limit: str = "") -> ParameterError:
    """The refusal of a record longer than :data:`MAX_SAMPLES` (``count``: how long it is, ending in a verb;
    ``limit``: the limit in this record's terms), naming the window that fixes it (``start``, ``end``)."""
    return ParameterError(
        f"{path}: {count} more than one identification takes ({limit}the exact likelihood of the kernel candidates "
        "costs O(N²)); identify a window of the trial (trial.window(start, end), s from its first sample), e.g. a "
        "stretch that holds the motion and the disturbance of interest", "start", "end")


def _signals(trial, form: str | None, method: str) -> tuple[str, np.ndarray, str]:
    """Step 1: the input form (``form`` or the trial's) and its exogenous signal (``v_ref`` or ``u``)
    with its name, after checking ``method``, ``form`` and the record: every sample finite, at most
    :data:`MAX_SAMPLES`, no sequence gap."""
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
    exo_max, exo_unit = (PHYSICAL.u_max, "N") if exo_name == "u" else (PHYSICAL.v_max, "m/s")
    absurd = (np.abs(v) > PHYSICAL.v_max) | (np.abs(exo) > exo_max)
    if absurd.any():  # (least squares would call such a column "collinear")
        k = int(np.argmax(absurd))
        raise ValueError(f"{trial.path}: {int(absurd.sum())} sample(s) with an absurd magnitude, first at seq "
                         f"{int(trial.seq[k])} (v_meas = {v[k]:.6g} m/s, {exo_name} = {exo[k]:.6g} {exo_unit}; limits "
                         f"{PHYSICAL.v_max:g} m/s, {exo_max:g} {exo_unit}): a recording or unit fault; identify a window "
                         "without it (trial.window(start, end)) or fix the file")
    Ts = float(trial.meta.Ts)
    if v.size - 1 > MAX_SAMPLES:
        raise too_long(trial.path, f"{v.size} samples ({v.size * Ts:.0f} s) are",
                       f"{MAX_SAMPLES} samples, {MAX_SAMPLES * Ts:.0f} s at this rate: ")
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


def _friction_columns(v: np.ndarray, Ts: float, omega: float | None, coulomb: bool | None,
                      notes: list[str]) -> tuple[float, bool, str, bool]:
    """Step 2: the dead band Ω used (``omega`` or :func:`dead_band`), whether the Coulomb columns are kept
    (``coulomb``, or when the trial reverses direction), the note saying why, and whether the trial rests
    (the Coulomb asymmetry can then be told from the offset: :func:`kernels.feed_drive.friction_transform`)."""
    omega_used = dead_band(v) if omega is None else float(omega)
    if not (math.isfinite(omega_used) and 0 <= omega_used <= OMEGA_MAX):
        raise ParameterError(f"omega must be a dead band 0 … {OMEGA_MAX:g} m/s, got {omega!r}", "omega")
    n_pos = int(np.sum(v[:-1] > omega_used))
    n_neg = int(np.sum(v[:-1] < -omega_used))
    reversal = n_pos >= MIN_REVERSAL_SAMPLES and n_neg >= MIN_REVERSAL_SAMPLES
    if coulomb is None:
        coulomb_used = reversal
        coulomb_note = ("Coulomb columns kept (trial reverses direction)" if reversal else
                        f"Coulomb columns dropped: no speed reversal ({n_pos} samples above +Ω, {n_neg} below −Ω); "
                        "the constant column holds the friction of the direction of motion")
        if not reversal:
            notes.append(coulomb_note)
    else:
        coulomb_used = bool(coulomb)
        coulomb_note = "Coulomb columns " + ("kept" if coulomb_used else "dropped") + " as requested"
        if coulomb_used and not reversal:
            empty = "-sigma_n" if n_neg < MIN_REVERSAL_SAMPLES else "-sigma_p"
            raise ParameterError(f"coulomb=True: the trial has no speed reversal ({n_pos} samples above +Ω, {n_neg} "
                                 f"below −Ω), so the Coulomb column {empty!r} cannot be identified; use coulomb=False "
                                 "(or None: identify chooses) or record a trial with reversals", "coulomb")
    rest = coulomb_used and rest_samples(v[:-1], omega_used, Ts) >= MIN_REST_SAMPLES
    if coulomb_used and not rest:
        notes.append("the trial has no rest (only passes through ±Ω during reversals): the Coulomb asymmetry "
                     "cannot be told from the force offset — coulomb_pos = coulomb_neg = the symmetric Coulomb "
                     "friction, and offset holds asymmetry + offset")
    return omega_used, coulomb_used, coulomb_note, rest


def _periods_to_try(trial, ls_resid: np.ndarray, Ts: float, duration: float, psis: list[float], psi_source: str,
                    notes: list[str]) -> tuple[list[float], str, int, list]:
    """Step 4: the periods the kernel candidates are tuned at, their source and ``k_period`` (1 when the
    period was found in the data: one more fitted hyperparameter), and the periods found in the LS
    residual ``ls_resid`` (within two samples and :data:`MAX_PERIOD_FRACTION` of the record). Without a
    given or spindle period the strongest one found is used; notes say so, say when none is found, and
    when a given period is locked to the motion."""
    ref = trial.v_ref[:-1] if trial.v_ref is not None and np.all(np.isfinite(trial.v_ref)) else None
    try:
        detected, motion = detect_periods(ls_resid, Ts, reference=ref)
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
                          ls: Candidate, *, tune: bool, progress) -> Candidate | None:
    """Step 6a: with a given or spindle period, the locally periodic candidate at the period found in the
    data when it is more than 2 % from every period tuned (validity rule 2 applied), else None."""
    if psi_source not in ("given", "spindle") or not detected:
        return None
    found = detected[0]
    if any(abs(psi - found.period) <= 0.02 * found.period for psi in psis):
        return None
    alt = prob.tuned("locally_periodic", found.period, init, tune=tune, k_extra=1, progress=progress,
                     label=f"locally periodic ψ = {found.period:.6g} s")
    _invalidate(alt, _efficiency_check(alt, ls))
    return alt


def _weigh_alternative(alt: Candidate, candidates: list[Candidate], trial, psis: list[float], psi_source: str,
                       spindle_rpm: float | None, notes: list[str]) -> tuple[bool, float | None]:
    """Step 6b: ``(off_spindle, suggested)`` for the candidate at the period found in the data.

    A speed read from the samples or the trial's metadata is a presumption about the disturbance, not the
    user's word: when the data clearly prefer another period (by :data:`SUGGEST_MARGIN` over every
    candidate locked to the spindle) that is not a (folded) harmonic of the spindle line, the disturbance
    does not follow the spindle (a shaker, a pump, a neighbouring machine) and that period competes like
    any other (``off_spindle``). Otherwise ``alt`` is listed but not eligible, and a period the user gave
    is kept, with the better one named (``suggested``) when it is valid and wins by the margin."""
    locked = max((c for c in candidates if c.kernel in PERIODIC_KINDS or c.kernel == "spindle"),
                 key=lambda c: c.log_evidence)
    margin = alt.log_evidence - locked.log_evidence
    teeth = int(trial.meta.teeth or 1)
    # a (folded) harmonic of the spindle line follows the spindle: the periodic kernel at ψ has it
    related = psi_source == "spindle" and any(
        sampled_harmonic(alt.period, psi, float(trial.meta.Ts), max_harmonic=max(8, 2 * teeth)) for psi in psis)
    if psi_source == "spindle" and spindle_rpm is None and margin > SUGGEST_MARGIN and not related:
        notes.append(f"the disturbance does not follow the spindle: ψ = {alt.period:.6g} s, found in the data, "
                     f"explains it better than every model locked to the spindle's speed (log evidence "
                     f"{margin:+.1f} over the {locked.label}); that period competes like any other, and the "
                     "tracker runs on time, not on the spindle's angle")
        return True, None
    suggested = None
    if related:
        notes.append(f"the line found at {1 / alt.period:.5g} Hz is a harmonic of the spindle's (as sampled, "
                     "folded at half the sample rate): the spindle period explains it")
    elif alt.valid and margin > SUGGEST_MARGIN:
        suggested = alt.period
        notes.append(f"the data prefer ψ = {alt.period:.6g} s to the {psi_source} period (log evidence "
                     f"{margin:+.1f} over the {locked.label}); check the period (--period {alt.period:.6g})")
    source = {"given": "--period", "spindle": "the spindle speed"}[psi_source]
    alt.notes.append(f"ψ = {alt.period:.6g} s was found in the data; not a choice, the period comes from {source}")
    alt.eligible = False
    return False, suggested


def _invalidate(cand: Candidate, why: str | None) -> None:
    """Mark ``cand`` invalid for ``why`` (kept after any earlier reason); nothing when ``why`` is None."""
    if why:
        cand.valid = False
        cand.why_not = why if cand.why_not is None else f"{cand.why_not}; {why}"


def _choose(candidates: list[Candidate], method: str) -> tuple[Candidate | None, str | None, Candidate | None,
                                                               Candidate | None]:
    """Step 7: ``(chosen, refusal, pl_best, written)`` — the valid candidate of ``method``'s pool with the
    highest evidence (None, with the refusal saying why, when none is valid), the best PL-LSSVM candidate
    (the best valid one, else the best; for the report), and the candidate written to the model file (the
    chosen one, else, for ``--force``, the best of the pool)."""
    pool = {"auto": candidates, "ls": candidates[:1], "pl-lssvm": candidates[1:]}[method]
    valid = [c for c in pool if c.valid]
    chosen = max(valid, key=lambda c: c.log_evidence) if valid else None
    refusal = None
    if chosen is None:
        best = max(pool, key=lambda c: c.log_evidence) if pool else None
        what = {"auto": "no candidate", "ls": "the LS model", "pl-lssvm": "no PL-LSSVM candidate"}[method]
        refusal = f"{what} is a valid model of this drive" + (f": {best.label}: {best.why_not}" if best else "")
        ls = candidates[0]
        if method == "auto" and best is not None and best is not ls:  # its advice may name LS: say why LS is not
            refusal += f"; {ls.label}: {ls.why_not}"
    pl_pool = [c for c in candidates if c.method == "pl_lssvm"]
    pl_best = None
    if pl_pool:
        pl_valid = [c for c in pl_pool if c.valid]
        pl_best = max(pl_valid or pl_pool, key=lambda c: c.log_evidence)
    written = chosen if chosen is not None else (max(pool, key=lambda c: c.log_evidence) if pool else None)
    return chosen, refusal, pl_best, written


def _low_speed_check(prob: _Problem, res: MethodResult | None, notes: list[str]) -> LowSpeedFriction | None:
    """The low-speed friction check (:mod:`kernels.low_speed`) on the written model's prediction error;
    a note when the friction law does not hold near standstill (and whether the monitor then learns
    β only above ``min_speed``)."""
    if res is None:
        return None
    err = prob.y - res.prediction
    if not np.all(np.isfinite(err)):
        return None
    check = low_speed_friction(prob.Z, err, prob.v[:-1], prob.omega)
    if check is None or not check.significant:
        return check
    if prob.form == "force-input" or prob.gain is not None:  # a·h is a force δ·sign(v) as a disturbance: δ = a/b
        delta = -float(disturbance_to_force(prob.form, res.beta, check.amplitude, gain=prob.gain))
        size = f"{abs(delta):.3g} N {'above' if delta > 0 else 'below'}"
    else:
        size = f"{'above' if check.amplitude > 0 else 'below'} (by {abs(check.amplitude):.3g} m/s per sample; give " \
               "--loop-gain for N)"
    what = (f"the friction law (Coulomb + viscous) does not hold near standstill: below about {check.speed:.3g} m/s "
            f"the friction is {size} the law (log-likelihood gain {check.gain:.0f})")
    if check.local:
        notes.append(f"{what}; the monitor learns β only above min_speed = {check.min_speed:.3g} m/s "
                     f"({100 * check.share:.0f} % of the motion is slower)")
    else:
        notes.append(f"{what}, but {100 * check.share:.0f} % of the motion is that slow: not a low-speed effect "
                     "to leave out (min_speed stays 0); it may be a disturbance that follows the feed")
    return check


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
            ll = reml_terms(None, None, LocallyPeriodic(s1, s2, q), cand.gamma, prob.Ts,
                            _prepared=prob.prepared).log_likelihood
        except ValueError:
            continue
        if ll > cand.log_likelihood:
            alt = prob.tuned("locally_periodic", q, {"sigma1": s1, "sigma2": s2, "gamma": cand.gamma}, tune=True,
                             k_extra=1, progress=progress, label=f"locally periodic ψ = {q:.6g} s")
            alt.notes.append(f"ψ = {q:.6g} s ({m}× the line found at {psi:.6g} s) explains the residual better")
            if alt.log_evidence > best.log_evidence:
                best = alt
    return best


# ------------------------------------------------------------------------------------------------
# truth
# ------------------------------------------------------------------------------------------------
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


def _aligned(truth, seq: np.ndarray, name: str) -> np.ndarray | None:
    """Truth column ``name`` at the samples ``seq`` (NaN where the truth has no value)."""
    col = getattr(truth, name, None)
    if col is None:
        return None
    out = np.full(seq.size, np.nan)
    pos = np.searchsorted(truth.seq, seq)
    ok = (pos < truth.seq.size) & (truth.seq[np.minimum(pos, truth.seq.size - 1)] == seq)
    out[ok] = col[pos[ok]]
    return out


def _corr(a, b) -> float | None:
    if a is None or b is None:
        return None
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.std(a[ok]) == 0 or np.std(b[ok]) == 0:
        return None
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def _true_physical(ident: Identification, truth_meta) -> dict:
    """The truth in the keys of :meth:`kernels.feed_drive.Physical.to_dict` (offset 0 in a simulation)."""
    p = dict(truth_meta.physical)
    out = {}
    scale = 1.0
    suffix = ""
    if ident.form == "velocity-loop" and ident.loop_gain is None:
        K = p.get("loop_gain")
        if not K:
            return {}
        scale, suffix = 1.0 / K, "_over_gain"
    for k in ("inertia", "damping"):
        if k in p:
            out[k + suffix] = p[k] * scale
    if ident.coulomb and "coulomb_pos" in p and "coulomb_neg" in p:
        out["coulomb_pos" + suffix] = p["coulomb_pos"] * scale
        out["coulomb_neg" + suffix] = p["coulomb_neg"] * scale
        out["coulomb" + suffix] = 0.5 * (p["coulomb_pos"] + p["coulomb_neg"]) * scale
        out["offset" + suffix] = 0.0
    return out


def _attach_truth(ident: Identification, trial) -> None:
    """Errors against the recorded truth (simulated trials, instrumented real ones) and against a
    published reference when the trial's provenance carries one (``reference_M``, ``reference_Fv``,
    ``reference_Fc``, ``reference_offset``)."""
    truth_meta = trial.meta.truth
    seq_k = trial.seq[:-1]  # z(k) rows: the disturbance of step k
    if trial.truth is not None:
        ident.truth_force = _aligned(trial.truth, seq_k, "force")
        ident.truth_f = _aligned(trial.truth, seq_k, "f")
        ident.measured_force = _aligned(trial.truth, seq_k, "dynamometer")
    doc: dict = {}
    results = {"ls": ident.ls, "pl_lssvm": ident.pl, "model": ident.model_result}
    if truth_meta is not None:
        phys_true = _true_physical(ident, truth_meta)
        doc["physical"] = phys_true
        doc["coulomb"] = truth_meta.coulomb
        p = truth_meta.physical
        try:
            true_beta = physical_to_beta(ident.form, ident.Ts, p["inertia"], p["damping"], gain=p.get("loop_gain"),
                                         coulomb_pos=p.get("coulomb_pos", 0.0), coulomb_neg=p.get("coulomb_neg", 0.0),
                                         coulomb=ident.coulomb, intercept=True)
        except (KeyError, ValueError):
            true_beta = None
        if true_beta is not None:
            doc["beta"] = true_beta.tolist()
        for key, res in results.items():
            if res is None:
                continue
            if true_beta is not None:
                n_cmp = 2 if not (ident.coulomb and truth_meta.coulomb) else true_beta.size - 1
                err = np.abs(res.beta[:n_cmp] - true_beta[:n_cmp])  # absolute where the true value is 0 (as below)
                rel = np.divide(err, np.abs(true_beta[:n_cmp]), out=err.copy(), where=true_beta[:n_cmp] != 0)
                doc[f"{key}_beta_rel_error"] = rel.tolist()
            errs = {}
            for name, value in res.physical.items():
                ref = phys_true.get(name)
                if ref is None:
                    continue
                errs[name] = abs(value - ref) / abs(ref) if ref else abs(value - ref)
            doc[f"{key}_physical_error"] = errs
    details = getattr(trial.meta.provenance, "details", {}) or {}
    ref_map = {"inertia": "reference_M", "damping": "reference_Fv", "coulomb": "reference_Fc", "offset": "reference_offset"}
    reference = {k: float(details[v]) for k, v in ref_map.items() if isinstance(details.get(v), (int, float))}
    if reference:
        doc["reference"] = reference
        for key, res in results.items():
            if res is None:
                continue
            doc[f"{key}_reference_error"] = {
                k: (res.physical[k] - r) / abs(r) if k != "offset" else res.physical[k] - r
                for k, r in reference.items() if k in res.physical}
    for key, res in results.items():
        if res is None or res.f is None:
            continue
        corr = _corr(res.f, ident.truth_f) if ident.truth_f is not None else _corr(res.f_force, ident.truth_force)
        if corr is not None:
            doc[f"{key}_disturbance_correlation"] = corr
        fc = _corr(res.f_force, ident.truth_force)
        if fc is not None:
            doc[f"{key}_force_correlation"] = fc
    model = ident.model_result
    if model is not None and model.f is not None:
        if "model_disturbance_correlation" in doc:
            doc["disturbance_correlation"] = doc["model_disturbance_correlation"]
        if "model_force_correlation" in doc:
            doc["force_correlation"] = doc["model_force_correlation"]
    ident.truth = doc or None

