"""Offline identification of one axis: LS and PL-LSSVM on a recorded trial (method §2–4).

:func:`identify` takes a :class:`feedio.mcapio.Trial` and returns an
:class:`Identification` with β per method, physical parameters, prediction
errors, the disturbance estimate and, for simulated trials, the error against
the recorded truth. :meth:`Identification.to_json` is the machine-readable
document of ``feedmon identify --json``; :meth:`Identification.to_model` the
model file for ``feedmon run``.
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field

import numpy as np

from kernels import LocallyPeriodic
from kernels.feed_drive import (
    beta_to_physical,
    disturbance_to_force,
    predict_one_step,
    regressors,
    simulate_free_run,
)
from kernels.least_squares import least_squares
from kernels.likelihood import log_marginal_likelihood
from kernels.likelihood import tune as tune_hyperparameters
from kernels.pl_lssvm import pl_lssvm

from . import online_settings as OS
from .model_file import AxisModel, TrackerConfig, file_sha256

__all__ = ["THESIS_DEFAULTS", "TRACKER_DEFAULTS", "Identification", "identify", "disturbance_period", "dead_band"]

#: PL-LSSVM hyperparameters when neither given nor tuned (thesis Table 4.1, case study 1)
THESIS_DEFAULTS = {"sigma1": 0.59, "sigma2": 0.42, "gamma": 50.3}
#: online KRLS-T defaults (one definition: monitor.online_settings)
TRACKER_DEFAULTS = OS.TRACKER_DEFAULTS
#: samples needed beyond ±Ω on each side before the Coulomb columns are identifiable
MIN_REVERSAL_SAMPLES = 20


def disturbance_period(meta, period: float | None = None, spindle_rpm: float | None = None) -> tuple[float, str]:
    """ψ (s) and where it came from: ``--period``, then ``--spindle-rpm``, then the trial metadata.

    With tool runout the cutting force repeats once per spindle revolution, so ψ = 60/rpm
    (not the tooth period).
    """
    if period is not None:
        if not (math.isfinite(period) and period > 0):
            raise ValueError(f"--period must be a positive number of seconds, got {period!r}")
        return float(period), "--period"
    if spindle_rpm is not None:
        if not (math.isfinite(spindle_rpm) and spindle_rpm > 0):
            raise ValueError(f"--spindle-rpm must be positive, got {spindle_rpm!r}")
        return 60.0 / spindle_rpm, "--spindle-rpm"
    if meta.spindle_rpm:
        return 60.0 / meta.spindle_rpm, "trial metadata (spindle_rpm)"
    raise ValueError(
        "no disturbance period: the trial has no spindle speed in its metadata; give --period S "
        "(e.g. --period 0.018182 for a 55 Hz shaker) or --spindle-rpm R --teeth N"
    )


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


@dataclass
class MethodResult:
    name: str
    beta: np.ndarray
    stderr: np.ndarray | None
    physical: dict
    rmse_linear: float  # y − Zβ (m/s)
    rmse: float  # one-step prediction error (m/s), with the disturbance for PL-LSSVM
    rmse_free_run: float  # free-run simulation error (m/s)
    prediction: np.ndarray  # one-step velocity prediction aligned with y
    physical_error: str | None = None

    def to_json(self) -> dict:
        out = {"beta": self.beta.tolist(), "physical": self.physical, "rmse": self.rmse,
               "rmse_linear": self.rmse_linear, "rmse_free_run": self.rmse_free_run}
        if self.stderr is not None:
            out["stderr"] = self.stderr.tolist()
        if self.physical_error:
            out["physical_error"] = self.physical_error
        return out


@dataclass
class Identification:
    """Everything ``feedmon identify`` found on one axis of a trial."""

    trial_path: str
    machine: str
    axis: str
    form: str
    Ts: float
    period: float
    period_source: str
    omega: float
    coulomb: bool
    coulomb_note: str
    names: tuple[str, ...]
    loop_gain: float | None
    hyperparameters: dict
    ls: MethodResult
    pl: MethodResult
    y: np.ndarray  # v_m(k+1), m/s
    t: np.ndarray  # time of y (s)
    f: np.ndarray  # PL-LSSVM disturbance estimate (m/s), aligned with y
    f_force: np.ndarray | None  # the same in N when scalable
    truth: dict | None = None
    truth_force: np.ndarray | None = None  # true disturbance force (N) aligned with y
    truth_f: np.ndarray | None = None  # true disturbance (m/s) aligned with y
    measured_force: np.ndarray | None = None  # e.g. dynamometer (N) aligned with y
    notes: list[str] = field(default_factory=list)
    spindle: dict | None = None  # {"teeth", "spindle_rpm"} when the trial's samples carry spindle data

    def to_json(self) -> dict:
        doc = {
            "trial": self.trial_path,
            "machine": self.machine,
            "axis": self.axis,
            "form": self.form,
            "Ts": self.Ts,
            "period": self.period,
            "period_source": self.period_source,
            "omega": self.omega,
            "coulomb": self.coulomb,
            "beta_names": list(self.names),
            "loop_gain": self.loop_gain,
            "hyperparameters": self.hyperparameters,
            "ls": self.ls.to_json(),
            "pl_lssvm": self.pl.to_json(),
            "notes": self.notes,
        }
        if self.truth is not None:
            doc["truth"] = self.truth
        return doc

    def to_model(self, *, method: str = "pl-lssvm", tracker: dict | None = None, feedmon_version: str = "") -> AxisModel:
        """The axis model file for ``feedmon run`` (β of ``method``, tracker defaults with ψ = period)."""
        chosen = self.pl if method == "pl-lssvm" else self.ls
        cfg = OS.tracker_table(tuned=self.hyperparameters if self.hyperparameters.get("tuned") else None,
                               period=self.period, spindle=self.spindle)
        for key, value in (tracker or {}).items():  # explicit settings: kernel hyperparameters go into the kernel
            if key in cfg["kernel"] and key != "type":
                cfg["kernel"] = {**cfg["kernel"], key: value}
            else:
                cfg[key] = value
        kernel = cfg["kernel"]
        return AxisModel(
            machine=self.machine,
            axis=self.axis,
            form=self.form,
            Ts=self.Ts,
            beta=[float(b) for b in chosen.beta],
            omega=self.omega,
            coulomb=self.coulomb,
            loop_gain=self.loop_gain,
            method=method,
            tracker=TrackerConfig(kernel=kernel, gamma=cfg["gamma"], forgetting=cfg["forgetting"],
                                  budget=int(cfg["budget"]), jitter=cfg["jitter"]),
            physical={k: v for k, v in chosen.physical.items() if isinstance(v, (int, float)) and k != "pole"},
            identification={k: v for k, v in self.hyperparameters.items() if v is not None},
            provenance={
                "source": self.trial_path,
                "sha256": file_sha256(self.trial_path),
                "method": method,
                "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
                "feedmon_version": feedmon_version,
            },
        )


def _physical(form, beta, Ts, gain, coulomb) -> tuple[dict, str | None]:
    try:
        return beta_to_physical(form, beta, Ts, gain=gain, coulomb=coulomb).to_dict(), None
    except ValueError as exc:
        return {}, str(exc)


def _rmse(a: np.ndarray) -> float:
    return float(math.sqrt(np.mean(a * a)))


def _free_run(form, beta, v_meas, exo, omega, coulomb, f=None) -> float:
    sim = simulate_free_run(form, beta, v_meas[0], exo, omega=omega, coulomb=coulomb,
                            disturbance=None if f is None else np.append(f, 0.0))
    err = sim - v_meas
    return _rmse(err) if np.all(np.isfinite(err)) else math.inf


def identify(
    trial,
    *,
    form: str | None = None,
    period: float | None = None,
    spindle_rpm: float | None = None,
    sigma1: float | None = None,
    sigma2: float | None = None,
    gamma: float | None = None,
    tune: bool = False,
    coulomb: bool | None = None,
    omega: float | None = None,
    loop_gain: float | None = None,
    progress=None,
) -> Identification:
    """Identify β of one axis by LS and PL-LSSVM (method §3–4).

    ``coulomb=None`` keeps the Coulomb columns when the trial reverses direction
    (at least :data:`MIN_REVERSAL_SAMPLES` samples beyond ±Ω each way) and drops
    them otherwise, with a note; ``coulomb=True`` insists (and fails on a trial
    without reversal with the kernels' rank error). ``omega=None`` estimates the
    dead band with :func:`dead_band`. ``progress(evaluations, params, ll, best)``
    is called during ``tune``.
    """
    meta = trial.meta
    form = form or meta.form
    Ts = float(meta.Ts)
    psi, psi_source = disturbance_period(meta, period, spindle_rpm)
    if form == "force-input":
        if trial.u is None:
            raise ValueError(f"{trial.path}: the force-input form needs a force command 'u', which the trial lacks; "
                             "use --form velocity-loop")
        exo, exo_name = trial.u, "u"
    else:
        exo, exo_name = trial.v_ref, "v_ref"
    v = trial.v_meas
    bad = ~(np.isfinite(v) & np.isfinite(exo))
    if bad.any():
        raise ValueError(f"{trial.path}: {int(bad.sum())} sample(s) with missing or non-finite v_meas/{exo_name}, "
                         f"first at seq {int(trial.seq[np.argmax(bad)])}; identification needs a contiguous record")
    steps = np.diff(trial.seq)
    if steps.size and np.any(steps != 1):
        k = int(np.argmax(steps != 1))
        raise ValueError(f"{trial.path}: sequence gap after seq {int(trial.seq[k])}; identify a contiguous segment")

    gain = loop_gain if loop_gain is not None else meta.loop_gain
    if form == "force-input":
        gain = None
    omega_used = dead_band(v) if omega is None else float(omega)
    notes = []
    n_pos = int(np.sum(v[:-1] > omega_used))
    n_neg = int(np.sum(v[:-1] < -omega_used))
    reversal = n_pos >= MIN_REVERSAL_SAMPLES and n_neg >= MIN_REVERSAL_SAMPLES
    if coulomb is None:
        coulomb_used = reversal
        coulomb_note = ("Coulomb columns kept (trial reverses direction)" if reversal else
                        f"Coulomb columns dropped: no speed reversal ({n_pos} samples above +Ω, {n_neg} below −Ω)")
    else:
        coulomb_used = bool(coulomb)
        coulomb_note = "Coulomb columns " + ("kept" if coulomb_used else "dropped") + " as requested"
    if not coulomb_used and coulomb is None:
        notes.append(coulomb_note)

    reg = regressors(form, v, v_ref=trial.v_ref if form == "velocity-loop" else None,
                     u=trial.u if form == "force-input" else None, omega=omega_used, coulomb=coulomb_used)
    Z, y = reg.Z, reg.y

    ls = least_squares(Z, y, reg.names)
    hp = {"sigma1": sigma1, "sigma2": sigma2, "gamma": gamma, "period": psi, "tuned": bool(tune)}
    if tune:
        init = (sigma1 or THESIS_DEFAULTS["sigma1"], sigma2 or THESIS_DEFAULTS["sigma2"], gamma or THESIS_DEFAULTS["gamma"])
        tr = tune_hyperparameters(Z, y, Ts, psi, init=init, progress=progress, names=reg.names)
        hp.update(sigma1=tr.sigma1, sigma2=tr.sigma2, gamma=tr.gamma, log_likelihood=tr.log_likelihood,
                  evaluations=tr.evaluations, tune_seconds=tr.seconds)
    else:
        for key in ("sigma1", "sigma2", "gamma"):
            if hp[key] is None:
                hp[key] = THESIS_DEFAULTS[key]
        hp["log_likelihood"] = log_marginal_likelihood(Z, y, LocallyPeriodic(hp["sigma1"], hp["sigma2"], psi),
                                                       hp["gamma"], Ts, names=reg.names)
    kernel = LocallyPeriodic(hp["sigma1"], hp["sigma2"], psi)
    pl = pl_lssvm(Z, y, kernel, hp["gamma"], Ts=Ts, names=reg.names)

    ls_phys, ls_err = _physical(form, ls.beta, Ts, gain, coulomb_used)
    pl_phys, pl_err = _physical(form, pl.beta, Ts, gain, coulomb_used)
    ls_pred = predict_one_step(ls.beta, reg)
    pl_lin = predict_one_step(pl.beta, reg)
    ls_res = MethodResult("LS", ls.beta, ls.stderr, ls_phys, _rmse(y - ls_pred), _rmse(y - ls_pred),
                          _free_run(form, ls.beta, v, exo, omega_used, coulomb_used), ls_pred, ls_err)
    pl_res = MethodResult("PL-LSSVM", pl.beta, None, pl_phys, _rmse(y - pl_lin), _rmse(y - pl_lin - pl.f),
                          _free_run(form, pl.beta, v, exo, omega_used, coulomb_used, pl.f), pl_lin + pl.f, pl_err)

    scalable = form == "force-input" or gain is not None
    f_force = disturbance_to_force(form, pl.beta, pl.f, gain=gain) if scalable and pl.beta[0] > 0 else None

    ident = Identification(
        trial_path=str(trial.path), machine=trial.machine, axis=trial.axis, form=form, Ts=Ts, period=psi,
        period_source=psi_source, omega=omega_used, coulomb=coulomb_used, coulomb_note=coulomb_note,
        names=reg.names, loop_gain=gain, hyperparameters=hp, ls=ls_res, pl=pl_res, y=y,
        t=trial.t[1:], f=pl.f, f_force=f_force, notes=notes,
    )
    ident.spindle = _spindle(trial)
    _attach_truth(ident, trial)
    if not scalable and form == "velocity-loop":
        notes.append("loop gain K unknown: only J/K and B/K are identifiable (give --loop-gain to get J and B)")
    return ident


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


def _corr(a: np.ndarray, b: np.ndarray) -> float | None:
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.std(a[ok]) == 0 or np.std(b[ok]) == 0:
        return None
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def _attach_truth(ident: Identification, trial) -> None:
    """Errors against the recorded truth (simulated trials, instrumented real ones)."""
    truth_meta = trial.meta.truth
    seq_k = trial.seq[:-1]  # z(k) rows: the disturbance of step k
    if trial.truth is not None:
        ident.truth_force = _aligned(trial.truth, seq_k, "force")
        ident.truth_f = _aligned(trial.truth, seq_k, "f")
        ident.measured_force = _aligned(trial.truth, seq_k, "dynamometer")
    doc: dict = {}
    if truth_meta is not None:
        true_beta = np.asarray(truth_meta.beta, dtype=np.float64)
        doc["beta"] = true_beta.tolist()
        doc["physical"] = dict(truth_meta.physical)
        doc["coulomb"] = truth_meta.coulomb
        if true_beta.size == ident.ls.beta.size:
            for key, res in (("ls", ident.ls), ("pl_lssvm", ident.pl)):
                rel = np.abs(res.beta - true_beta) / np.maximum(np.abs(true_beta), 1e-300)
                doc[f"{key}_beta_rel_error"] = rel.tolist()
        else:
            doc["note"] = (f"true β has {true_beta.size} entries, the identified model {ident.ls.beta.size} "
                           "(Coulomb columns differ); compare the first two")
            for key, res in (("ls", ident.ls), ("pl_lssvm", ident.pl)):
                rel = np.abs(res.beta[:2] - true_beta[:2]) / np.abs(true_beta[:2])
                doc[f"{key}_beta_rel_error"] = rel.tolist()
        for key, res in (("ls", ident.ls), ("pl_lssvm", ident.pl)):
            errs = {}
            for name, value in res.physical.items():
                ref = truth_meta.physical.get(name)
                if isinstance(ref, (int, float)) and ref and isinstance(value, (int, float)):
                    errs[name] = abs(value - ref) / abs(ref)
            doc[f"{key}_physical_rel_error"] = errs
    if ident.truth_f is not None:
        doc["disturbance_correlation"] = _corr(ident.f, ident.truth_f)
    elif ident.truth_force is not None and ident.f_force is not None:
        doc["disturbance_correlation"] = _corr(ident.f_force, ident.truth_force)
    if ident.truth_force is not None and ident.f_force is not None:
        doc["force_correlation"] = _corr(ident.f_force, ident.truth_force)
    ident.truth = doc or None
