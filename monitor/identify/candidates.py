"""The candidates of one identification: the regression all of them share (:class:`_Problem`), a candidate
evaluated on it (:class:`Candidate`), its fit (:class:`MethodResult`) and the constants of the rules
(docs/method.md §8)."""

from __future__ import annotations

import math
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import qr

from kernels.feed_drive import (
    beta_to_physical,
    disturbance_to_force,
    physical_covariance,
    simulate_free_run,
    validity_problems,
)
from kernels.likelihood import PERIODIC_KINDS, _make_kernel, default_bounds, log_evidence, reml_terms
from kernels.likelihood import tune as tune_hyperparameters
from kernels.pl_lssvm import pl_lssvm, prepare_regression

THESIS_DEFAULTS = {"sigma1": 0.59, "sigma2": 0.42, "gamma": 50.3}
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
#: highest order m of the likelihood while tuning (the order-m approximation, kernels.levinson: exact for
#: records up to TUNE_ORDER + 1 samples and for kernels whose memory is shorter)
TUNE_ORDER = 2048
#: highest order of a candidate's evaluation (its evidence, β and covariance) and of the polish steps
FINAL_ORDER = 8192
#: the lags beyond the order used add less than this to log|A| (eq. V3 of kernels.levinson), log-likelihood
#: units: while tuning (the optimum moves less than the objective's error) and for the evidence
TUNE_TOL, ORDER_TOL = 2.0, 0.5
#: Nelder–Mead evaluations at FINAL_ORDER from the tuned optimum, when the tuning order held the kernel's memory back
POLISH_EVALUATIONS = 6
#: Nelder–Mead evaluations of a tuning (from a design of starts) and of a refinement (from a related optimum)
TUNE_EVALUATIONS, REFINE_EVALUATIONS = 30, 20
#: a longer record is tuned on the window of this many samples with the most disturbance (the first
#: difference of the LS residual), and the tuned values polished and evaluated on the whole record
TUNE_WINDOW = 65_536
#: the kernel's memory (σ1, the squared exponential's length) is bounded so that its support — where it
#: exceeds 10⁻³ of k(0), √(2 ln 1000) ≈ 3.7 σ1 — fits in FINAL_ORDER lags, when the record is longer: a longer
#: memory is beyond what the order-m likelihood resolves (tuning would wander there)
SUPPORT_SIGMAS = 3.7

_METHOD_LABEL = {"ls": "LS", "pl_lssvm": "PL-LSSVM"}


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
    order: int = 0  # order m of its likelihood (kernels.levinson; N − 1: exact, 0: least squares)
    theta: np.ndarray | None = None  # the coefficients of the identifiable columns (β = T θ; nuisance ones too)

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


def busiest_window(resid: np.ndarray, size: int) -> tuple[int, int]:
    """``(a, b)``: the ``size`` consecutive samples of ``resid`` whose first difference carries the most
    energy (a disturbance, not a slow drift), the whole record when it is shorter."""
    n = resid.size
    if n <= size:
        return 0, n
    energy = np.concatenate([[0.0], np.cumsum(np.diff(resid) ** 2)])  # energy[k] = Σ_{j<k} Δr_j²
    sums = energy[size - 1:] - energy[: energy.size - size + 1]
    a = int(np.argmax(sums))
    return a, a + size


def _independent_columns(Z: np.ndarray) -> np.ndarray:
    """Indices of a set of numerically independent columns of ``Z`` (pivoted QR on unit-norm columns): a window
    may hold a column that is constant there (a process acting all through it) or empty (no reversal)."""
    norms = np.sqrt(np.sum(Z * Z, axis=0))
    live = np.flatnonzero(norms > 0)
    _, R, piv = qr(Z[:, live] / norms[live], mode="economic", pivoting=True, check_finite=False)
    diag = np.abs(np.diag(R))
    rank = int(np.sum(diag > 1e-9 * diag[0]))
    return np.sort(live[piv[:rank]])


class _Problem:
    """The regression of one trial shared by all candidates."""

    def __init__(self, form, Ts, gain, names, T, Z_id, id_names, y, exo, v, omega, coulomb, gate=None, keep=None):
        self.form, self.Ts, self.gain, self.names, self.T = form, Ts, gain, names, T
        self.Z, self.id_names, self.y, self.exo, self.v = Z_id, id_names, y, exo, v
        self.omega, self.coulomb = omega, coulomb
        self.gate = gate  # where the disturbance acts (kernels.blocks), None: everywhere
        self.keep = keep  # the samples in the fit (the friction law holds there), None: all
        self._window = None
        self.prepared = prepare_regression(Z_id, y, id_names)
        self.n, self.p = Z_id.shape

    def terms(self, kernel, gamma, phase=None):
        """The REML terms of a kernel at the final order (:data:`FINAL_ORDER`, :data:`ORDER_TOL`)."""
        return reml_terms(None, None, kernel, gamma, self.Ts, phase=phase, gate=self.gate, keep=self.keep,
                          max_order=FINAL_ORDER, tol=ORDER_TOL, _prepared=self.prepared)

    def candidate(self, method, kernel_kind, kernel, gamma, hyper, k, notes=(), terms=None, phase=None) -> Candidate:
        if terms is None:
            terms = self.terms(kernel, gamma, phase) if kernel is not None else reml_terms(
                None, None, None, None, self.Ts, keep=self.keep, _prepared=self.prepared)
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
                         kernel_object=kernel, gamma=gamma, vif=vif, phase=phase, order=terms.order,
                         theta=np.asarray(terms.beta))
        if problems:
            cand.valid, cand.why_not = False, "; ".join(problems)
        return cand

    def tuning_window(self) -> tuple[_Problem, int, int]:
        """``(problem, a, b)``: this one, or for a record longer than :data:`TUNE_WINDOW` the window of its
        samples ``a … b − 1`` with the most disturbance (:func:`busiest_window` of the LS residual), with the
        columns that are independent there."""
        if self.n <= TUNE_WINDOW:
            return self, 0, self.n
        if self._window is None:
            kept = slice(None) if self.keep is None else self.keep
            theta = np.linalg.lstsq(self.Z[kept], self.y[kept], rcond=None)[0]
            a, b = busiest_window(self.y - self.Z @ theta, TUNE_WINDOW)
            cols = _independent_columns(self.Z[a:b] if self.keep is None else self.Z[a:b][self.keep[a:b]])
            sub = _Problem(self.form, self.Ts, self.gain, self.names, self.T[:, cols], self.Z[a:b, cols],
                           tuple(self.id_names[c] for c in cols), self.y[a:b], self.exo[a:b + 1], self.v[a:b + 1],
                           self.omega, self.coulomb, gate=None if self.gate is None else self.gate[a:b],
                           keep=None if self.keep is None else self.keep[a:b])
            self._window = (sub, a, b)
        return self._window

    def bounds(self, kind, period, phase, order: int = FINAL_ORDER) -> dict:
        """:func:`kernels.likelihood.default_bounds` of the record, the memory's upper bound held within
        what ``order`` lags resolve (:data:`SUPPORT_SIGMAS`) when the record is longer."""
        span = None
        if kind == "spindle":
            psi = phase.periods(period)
            psi = psi[np.isfinite(psi) & (phase.lengths > 1)]
            span = (float(psi.max()), float(psi.min())) if psi.size else (1.0, 1.0)
        bounds = default_bounds(kind, self.n, self.Ts, span if kind == "spindle" else period)
        if self.n - 1 > order:
            name = "lengthscale" if kind == "squared_exponential" else "sigma1"
            lo, hi = bounds[name]
            bounds[name] = (lo, min(hi, max(2.0 * lo, order * self.Ts / SUPPORT_SIGMAS)))
        return bounds

    def _tune(self, kind, period, init, progress, label, refine, phase):
        """REML tuning at :data:`TUNE_ORDER` — on the busiest window of a long record (:meth:`tuning_window`) —
        then, when that order held the kernel's memory back (the criterion V3 had not stopped it) or the
        tuning saw a window only, a few Nelder–Mead steps at :data:`FINAL_ORDER` on the whole record from the
        optimum (a short record's short-memory kernel's optimum is already final)."""
        report = None if progress is None else (lambda *a: progress(label, *a))
        sub, a, b = self.tuning_window()
        kw = dict(kind=kind, progress=report, tol=TUNE_TOL)
        # a window: the memory within what its tuning order resolves (its approximate likelihood would favour a
        # longer one that the whole record, at the final order, does not)
        bounds = self.bounds(kind, period, phase, FINAL_ORDER if sub is self else TUNE_ORDER)
        res = tune_hyperparameters(None, None, self.Ts, period, init=init, design=not refine, max_order=TUNE_ORDER,
                                   max_evaluations=REFINE_EVALUATIONS if refine else TUNE_EVALUATIONS,
                                   _prepared=sub.prepared, gate=sub.gate, keep=sub.keep, bounds=bounds,
                                   phase=None if phase is None else phase.window(a, b), **kw)
        kw.update(_prepared=self.prepared, gate=self.gate, keep=self.keep, phase=phase, tol=ORDER_TOL,
                  bounds=self.bounds(kind, period, phase))
        if sub is self:  # the whole record tuned: the evidence is evaluated at the final order (Problem.terms)
            return res, res.evaluations, res.seconds
        polished = tune_hyperparameters(None, None, self.Ts, period, init=dict(res.hyper, gamma=res.gamma),
                                        design=False, max_order=FINAL_ORDER, max_evaluations=POLISH_EVALUATIONS,
                                        step=0.15, **kw)
        return polished, res.evaluations + polished.evaluations, res.seconds + polished.seconds

    def tuned(self, kind, period, init, tune, k_extra, progress, label, refine: bool = False, phase=None) -> Candidate:
        """A kernel candidate: tuned by REML (or the given/thesis values), then evaluated at the final order
        (block-diagonally on the stretches ``phase`` for the spindle-phase kernel).
        ``refine``: ``init`` is a good start (the optimum of a related family): no start design, fewer
        evaluations."""
        notes = []
        if tune:
            res, evaluations, seconds = self._tune(kind, period, init, progress, label, refine, phase)
            hyper = dict(res.hyper, gamma=res.gamma, tuned=True, evaluations=evaluations,
                         tune_seconds=round(seconds, 3))
            if res.on_bound:
                hyper["on_bound"] = dict(res.on_bound)
            for name, side in res.on_bound.items():
                lo, hi = res.bounds[name]
                notes.append(f"{label}: {name} ended on its {side} bound ({lo if side == 'lower' else hi:.4g}): "
                             f"{_BOUND_MEANING[(name, side)]}")
            kernel, gamma = res.kernel(), res.gamma
            terms = res.terms if res.order < TUNE_ORDER or res.terms.tail_estimate < ORDER_TOL else None
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
        """Predictions (and, for PL-LSSVM, the disturbance estimate) of a candidate. The disturbance holds what
        the nuisance columns took (a process's mean force): ``f`` = GP part + nuisance part; ``linear`` is
        ``βᵀz``, what the monitor's residual is taken from."""
        theta = cand.theta
        f = None
        if cand.method == "pl_lssvm":  # the order of its likelihood: the same model
            res = pl_lssvm(self.Z, self.y, cand.kernel_object, cand.gamma, Ts=self.Ts, names=self.id_names,
                           solver="levinson", phase=cand.phase, order=cand.order, gate=self.gate, keep=self.keep)
            f, theta = res.f, res.beta
        spec = np.flatnonzero(np.any(self.T != 0.0, axis=0))
        nuisance = np.setdiff1d(np.arange(theta.size), spec)
        linear = self.Z[:, spec] @ theta[spec]
        if nuisance.size:
            part = self.Z[:, nuisance] @ theta[nuisance]
            f = part if f is None else f + part
        pred = linear + (f if f is not None else 0.0)
        kept = slice(None) if self.keep is None else self.keep  # the samples left out are not predicted
        with np.errstate(over="ignore", invalid="ignore"):  # an invalid (unstable) model diverges
            sim = simulate_free_run(self.form, cand.beta, self.v[0], self.exo, omega=self.omega,
                                    coulomb=self.coulomb, intercept=True,
                                    disturbance=None if f is None else np.nan_to_num(np.append(f, 0.0)))
            err = sim - self.v
            free = _rmse(err) if np.all(np.isfinite(err)) else math.inf
        if cand.method == "ls":
            f = None  # no disturbance model: a process mean is in the prediction, not shown as a disturbance
        f_force = None
        scalable = self.form == "force-input" or self.gain is not None
        if f is not None and scalable and cand.beta[0] > 0:
            f_force = disturbance_to_force(self.form, cand.beta, f, gain=self.gain)
        return MethodResult(name=_METHOD_LABEL[cand.method], candidate=cand, rmse_linear=_rmse((self.y - linear)[kept]),
                            rmse=_rmse((self.y - pred)[kept]), rmse_free_run=free, prediction=pred, f=f, f_force=f_force)


