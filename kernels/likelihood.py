"""Restricted marginal likelihood (REML) of the PL-LSSVM model, its tuning, and the evidence of a
candidate model (method §4; issue 10).

The PL-LSSVM model read as a Gaussian process with an explicit linear basis:

    y = Z̃ b + f + ε,    f ~ GP(0, s² k),    ε ~ N(0, s²/γ · I)   ⇒   cov(y) = s² A,  A = Ω + γ⁻¹I     (L1)

with ``Z̃ = [1, Z]`` (or ``Z`` when it has its own constant column ``one``) and ``b = [c; β]``; the
PL-LSSVM solution is the GLS / posterior mean of this model. Least squares is the same reading with
no kernel, ``A = I`` (white equation error). ``b`` is integrated out under a flat prior (REML) and
the scale ``s²`` is profiled out in closed form, ``ŝ² = yᵀPy/(N − p)``:

    ℓ(θ) = −½ [ (N − p)(log(2π ŝ²) + 1) + log|A| + log|Z̃ᵀA⁻¹Z̃| − log|Z̃ᵀZ̃| ]                      (L2)

where ``yᵀPy = (y − Z̃b̂)ᵀA⁻¹(y − Z̃b̂)`` and ``p`` = columns of ``Z̃``. The ``− log|Z̃ᵀZ̃|`` term
(constant in θ) makes ℓ invariant to rescaling the regressor columns (Harville's form) and makes
the REML of different covariance models with the same ``Z̃`` comparable — LS gives
``ℓ_LS = −½ (N − p)(log(2π ŝ²) + 1)``.

GLS covariance of ``b`` (the uncertainty of β under the candidate, issue 10 item 4):

    cov(b̂) = ŝ² (Z̃ᵀA⁻¹Z̃)⁻¹                                                                   (L3)

(``ŝ² (Z̃ᵀZ̃)⁻¹`` for LS).

Evidence of a candidate (:func:`log_evidence`): the REML at the tuned hyperparameters with a
Laplace/BIC-style penalty for the ``k`` hyperparameters fitted to the data,

    log E = ℓ(θ̂) − ½ k log(N − p)                                                                (L4)

(``s²`` is profiled in every candidate and not counted; hyperparameters given by the user, or kept
with ``--no-tune``, count 0; a period found from the data counts 1).

Evaluation (:func:`reml_terms`): by **whitening** with the inverse Cholesky factor of the Toeplitz
``A`` from one Levinson–Durbin pass (:func:`kernels.toeplitz.levinson_whiten`), which gives
``L⁻¹[Z̃, y]`` and ``log|A|`` together; then a QR of the whitened ``Z̃`` gives ``b̂``, ``yᵀPy``,
``log|Z̃ᵀA⁻¹Z̃|`` and (L3). Exact, ``O(N² (p + 2))`` time, ``O(N p)`` memory, independent of the
conditioning of ``A`` (long σ1 and large γ stall PCG, not Levinson).

The spindle-phase kernel (:mod:`kernels.spindle_phase`, kind ``"spindle"``) on ``x = (t, θ)`` is
evaluated on the stretches of constant spindle speed (``phase``): block-diagonal ``A``, one exact
Levinson whitening per stretch with its own Toeplitz column (eq. S2), ``log|A| = Σ log|A_s|``.

Tuning (:func:`tune`) maximises the exact REML of the whole record. A block-diagonal (segmented)
approximation is available (``segment``: consecutive segments treated as independent realisations of
``f`` with a shared ``b``, ``log|A| = Σ log|A_s|``, one Levinson pass of the segment length for all
of them, ``O(segment · N · (p+1))``) but not used by default: when γ is large (the kernel explains
nearly all of the residual, as on smooth real data) it misjudges the long-range correlation σ1 by
thousands of log-likelihood units — every segment start forgets the periodic pattern.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import solve_triangular
from scipy.optimize import minimize

from .covariance import Kernel, LocallyPeriodic, SquaredExponential, ZeroMeanLocallyPeriodic
from .pl_lssvm import _check_gamma, prepare_regression
from .spindle_phase import PhaseSegments, spindle_phase_kernel
from .toeplitz import levinson_whiten

__all__ = ["log_marginal_likelihood", "reml_terms", "REMLTerms", "log_evidence", "tune", "TuneResult",
           "default_bounds", "KINDS", "PERIODIC_KINDS", "BOUND_RTOL"]

#: kernel families that can be tuned: hyperparameter names besides γ
KINDS = {"squared_exponential": ("lengthscale",), "locally_periodic": ("sigma1", "sigma2"),
         "locally_periodic_zero_mean": ("sigma1", "sigma2"), "spindle": ("sigma1", "sigma2")}
#: the families with a period ψ
PERIODIC_KINDS = ("locally_periodic", "locally_periodic_zero_mean")
#: a tuned value within this fraction (in log space, of the bound interval) of a bound "ends on it"
BOUND_RTOL = 0.01


@dataclass(frozen=True)
class REMLTerms:
    """The pieces of the restricted log likelihood (L2) and the GLS covariance (L3)."""

    log_likelihood: float
    s2: float  # profiled scale ŝ²
    logdet_A: float
    logdet_M: float  # log|Z̃ᵀA⁻¹Z̃|
    logdet_ZZ: float  # log|Z̃ᵀZ̃|
    quad: float  # yᵀPy
    n: int
    p: int
    b: np.ndarray  # [c; β] (or β when Z has its own constant column)
    cov: np.ndarray  # ŝ² (Z̃ᵀA⁻¹Z̃)⁻¹, (p, p)
    solver: str
    intercept: bool = False  # True when b[0] is the PL-LSSVM bias c (Z has no constant column)

    @property
    def beta(self) -> np.ndarray:
        return self.b[1:] if self.intercept else self.b

    @property
    def beta_cov(self) -> np.ndarray:
        return self.cov[1:, 1:] if self.intercept else self.cov


def _logdet_scaled_gram(Zs: np.ndarray) -> float:
    R = np.linalg.qr(Zs, mode="r")
    return 2.0 * float(np.sum(np.log(np.abs(np.diag(R)))))


def reml_terms(Z, y, kernel: Kernel | None, gamma, Ts, *, names=None, segment: int | None = None,
               phase: PhaseSegments | None = None, _prepared=None) -> REMLTerms:
    """All terms of the REML log likelihood (L2) and the GLS covariance (L3) on a uniform time grid.

    ``kernel=None`` is least squares (``A = I``; ``gamma`` ignored). Otherwise ``kernel`` must be a
    time kernel (``kernel.is_stationary_1d``) and ``Ts`` the sample period (s). Exact (Levinson
    whitening of the whole record) unless ``segment`` is given: then the block-diagonal (segmented)
    approximation of the module docstring. With ``phase`` (the stretches of constant spindle speed),
    ``kernel`` is a kernel on ``(t, θ)`` (the spindle-phase kernel) evaluated block-diagonally.
    """
    if _prepared is None:
        _prepared = prepare_regression(Z, y, names)
    Z_arr, y, names, Zt, intercept = _prepared
    n, p = Zt.shape
    scale = np.sqrt(np.sum(Zt * Zt, axis=0))
    if kernel is None:
        b, quad, logdet_M_s, Rinv = _qr_terms(Zt / scale, y)
        return _assemble(Zt, b / scale, quad, 0.0, logdet_M_s, Rinv, scale, "least-squares", intercept)
    gamma = _check_gamma(gamma)
    if phase is not None:
        if phase.edges[-1] != n:
            raise ValueError(f"the spindle stretches cover {int(phase.edges[-1])} samples, the regression has {n}")
        white, logdet_A = _whiten_phase(Zt, y, kernel, gamma, float(Ts), phase)
        b, quad, logdet_M_s, Rinv = _qr_terms(white[:, :p] / scale, white[:, p])
        return _assemble(Zt, b / scale, quad, logdet_A, logdet_M_s, Rinv, scale, f"spindle-{phase.count}", intercept)
    if not kernel.is_stationary_1d:
        raise ValueError(f"{kernel!r} is not a time kernel; the likelihood is implemented for uniform time grids")
    Ts = float(Ts)
    if not (math.isfinite(Ts) and Ts > 0):
        raise ValueError(f"Ts must be a positive sample period in s, got {Ts!r}")
    if segment is None:
        segment, label = n, "levinson"
    else:
        segment = int(segment)
        if segment < 4 * p:
            raise ValueError(f"segment must be at least {4 * p} samples, got {segment}")
        segment = min(segment, n)
        label = None
    white, logdet_A, count = _whiten(Zt, y, kernel, gamma, Ts, segment)
    b, quad, logdet_M_s, Rinv = _qr_terms(white[:, :p] / scale, white[:, p])
    return _assemble(Zt, b / scale, quad, logdet_A, logdet_M_s, Rinv, scale, label or f"segmented-{count}",
                     intercept)


def _whiten(Zt, y, kernel, gamma, Ts, segment):
    """``L_s⁻¹[Z̃_s, y_s]`` for consecutive segments of ≤ ``segment`` samples (one Levinson–Durbin
    pass; exact when ``segment = N``) and ``Σ log|A_s|``."""
    n, p = Zt.shape
    count = max(1, -(-n // segment))
    edges = np.linspace(0, n, count + 1).astype(np.int64)
    lengths = np.diff(edges)
    lmax = int(lengths.max())
    column = kernel.lag(np.arange(lmax) * Ts)
    column[0] += 1.0 / gamma
    data = np.column_stack([Zt, y])
    series = np.zeros((count, p + 1, lmax))
    for i in range(count):
        series[i, :, :lengths[i]] = data[edges[i]:edges[i + 1]].T
    W, logdets = levinson_whiten(column, series, lengths)
    white = np.concatenate([W[i, :, :lengths[i]].T for i in range(count)], axis=0)
    return white, float(np.sum(logdets)), int(count)


def _whiten_phase(Zt, y, kernel, gamma, Ts, phase: PhaseSegments):
    """``L_s⁻¹[Z̃_s, y_s]`` and ``Σ log|A_s|`` over the stretches of constant spindle speed (eq. S2)."""
    data = np.column_stack([Zt, y])
    white = np.empty_like(data)
    logdet = 0.0
    edges = phase.edges.tolist()
    for (a, b), column in zip(zip(edges[:-1], edges[1:]), phase.columns(kernel, Ts, 1.0 / gamma)):
        W, logdets = levinson_whiten(column, data[a:b].T[None])
        white[a:b] = W[0].T
        logdet += float(logdets[0])
    return white, logdet


def _qr_terms(Zw: np.ndarray, yw: np.ndarray):
    """GLS on whitened, column-scaled data: ``b_s``, ``yᵀPy``, ``log|Z_wᵀZ_w|`` and ``R⁻¹``."""
    Q, R = np.linalg.qr(Zw)
    bs = solve_triangular(R, Q.T @ yw, check_finite=False)
    rw = yw - Zw @ bs
    logdet = 2.0 * float(np.sum(np.log(np.abs(np.diag(R)))))
    Rinv = solve_triangular(R, np.eye(R.shape[0]), check_finite=False)
    return bs, float(rw @ rw), logdet, Rinv


def _assemble(Zt, b, quad, logdet_A, logdet_M_scaled, Rinv, scale, solver, intercept) -> REMLTerms:
    n, p = Zt.shape
    if not quad > 0:
        raise ValueError("yᵀPy is not positive: the data are fitted exactly; the likelihood is undefined")
    logdet_ZZ_scaled = _logdet_scaled_gram(Zt / scale)
    two_log_scale = 2.0 * float(np.sum(np.log(scale)))
    dof = n - p
    s2 = quad / dof
    ll = -0.5 * (dof * (math.log(2.0 * math.pi * s2) + 1.0) + logdet_A + logdet_M_scaled - logdet_ZZ_scaled)
    cov = s2 * (Rinv @ Rinv.T) / np.outer(scale, scale)
    return REMLTerms(log_likelihood=ll, s2=s2, logdet_A=logdet_A, logdet_M=logdet_M_scaled - two_log_scale,
                     logdet_ZZ=logdet_ZZ_scaled + two_log_scale, quad=quad, n=n, p=p, b=b,
                     cov=0.5 * (cov + cov.T), solver=solver, intercept=bool(intercept))


def log_marginal_likelihood(Z, y, kernel, gamma, Ts, *, names=None, segment: int | None = None) -> float:
    """Restricted log marginal likelihood (L2) of the PL-LSSVM model with ``kernel`` and ``gamma``
    on a uniform grid of period ``Ts`` (``kernel=None``: least squares). Exact by default;
    ``segment`` selects the block-diagonal approximation (module docstring)."""
    return reml_terms(Z, y, kernel, gamma, Ts, names=names, segment=segment).log_likelihood


def log_evidence(log_likelihood: float, k: int, n: int, p: int) -> float:
    """(L4): ``ℓ − ½ k log(N − p)`` for ``k`` hyperparameters fitted to the data."""
    return float(log_likelihood) - 0.5 * int(k) * math.log(max(n - p, 2))


def default_bounds(kind: str, n: int, Ts: float, period: float | None = None) -> dict:
    """Hyperparameter bounds scaled to the record (issue 10 item 6), ``T = N Ts`` the record length.

    * locally periodic (and its zero-mean form): ``σ1 ∈ [2ψ, max(4ψ, T)]`` (from a couple of periods to the record: how long
      the periodic pattern stays correlated), ``σ2 ∈ [max(0.05, π Ts/(2ψ)), 5]`` (within-period
      smoothness ``σ2 ψ/π`` from half a sample, or 1/60 of a period, to nearly sinusoidal),
      ``γ ∈ [1e-2, 1e6]`` (disturbance-to-noise variance ratio);
    * squared exponential: ``ℓ ∈ [10 Ts, max(20 Ts, T)]``, ``γ ∈ [1e-2, 1e6]``;
    * spindle phase: those of the locally periodic kernel, ``period`` = (slowest, fastest) stretch
      period ψ (s): σ1 from the slowest, σ2 from the fastest.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown kernel family {kind!r}; use one of {', '.join(KINDS)}")
    record = n * Ts
    gamma = (1e-2, 1e6)
    if kind in PERIODIC_KINDS or kind == "spindle":
        if period is None:
            raise ValueError("the locally periodic kernel needs a period ψ")
        slow, fast = period if kind == "spindle" else (period, period)
        return {"sigma1": (2.0 * slow, max(4.0 * slow, record)),
                "sigma2": (max(0.05, math.pi * Ts / (2.0 * fast)), 5.0), "gamma": gamma}
    return {"lengthscale": (10.0 * Ts, max(20.0 * Ts, record)), "gamma": gamma}


def _make_kernel(kind: str, values: dict, period: float | None) -> Kernel:
    """The kernel of family ``kind``; ``period`` is ψ (s), for ``"spindle"`` the angle period P (rad)."""
    if kind == "spindle":
        return spindle_phase_kernel(values["sigma1"], values["sigma2"], period)
    if kind == "locally_periodic":
        return LocallyPeriodic(values["sigma1"], values["sigma2"], period)
    if kind == "locally_periodic_zero_mean":
        return ZeroMeanLocallyPeriodic(values["sigma1"], values["sigma2"], period)
    return SquaredExponential(values["lengthscale"])


@dataclass(frozen=True)
class TuneResult:
    """Maximum-likelihood hyperparameters of one kernel family (period fixed)."""

    kind: str
    hyper: dict  # kernel hyperparameters (sigma1, sigma2 | lengthscale)
    gamma: float
    log_likelihood: float  # the tuning objective at the optimum (exact REML unless segmented)
    evaluations: int
    period: float | None = None  # ψ (s); for "spindle" the angle period P (rad)
    seconds: float = 0.0
    segment: int = 0
    bounds: dict = field(default_factory=dict)
    on_bound: dict = field(default_factory=dict)  # name → "lower" | "upper"
    terms: REMLTerms | None = None  # exact REML terms at the optimum (None with a segmented objective)

    def kernel(self) -> Kernel:
        return _make_kernel(self.kind, self.hyper, self.period)

    @property
    def sigma1(self) -> float | None:
        return self.hyper.get("sigma1")

    @property
    def sigma2(self) -> float | None:
        return self.hyper.get("sigma2")


def tune(Z, y, Ts, period=None, *, kind: str = "locally_periodic", init: dict | None = None,
         bounds: dict | None = None, progress=None, names=None, segment: int | None = None,
         max_evaluations: int = 30, xatol: float = 0.1, fatol: float = 0.1, design: bool = True,
         phase: PhaseSegments | None = None, _prepared=None) -> TuneResult:
    """Maximise the REML (L2) over the log hyperparameters of ``kind`` and log γ.

    The objective is the exact REML of the whole record (``segment`` selects the block-diagonal
    approximation instead: faster, but it misjudges long correlation times σ1 when γ is large).
    Several starts: ``init`` (clipped into the bounds) and, with ``design``, a two-level design at ¼
    and ¾ of each log range (the 4 corners in 2-D, a half fraction of the 8 corners in 3-D); bounded
    Nelder–Mead from the best start (``xatol`` in log units, ``fatol`` in log likelihood) until
    ``max_evaluations``.
    ``on_bound`` names the values that end within ``BOUND_RTOL`` of a bound (in log space).

    Parameters
    ----------
    Z, y : regression data (method §2); ``Ts`` sample period (s); ``period`` ψ (s) for the locally
        periodic kernel; for ``"spindle"`` the angle period P (rad, default 2π: per revolution).
    kind : "locally_periodic", "locally_periodic_zero_mean", "squared_exponential" or "spindle"
        (the spindle-phase kernel on the stretches ``phase`` of constant spindle speed)
    init : dict, optional
        Starting values by name (e.g. ``{"sigma1": 0.59, "sigma2": 0.42, "gamma": 50.3}``).
    bounds : dict name → (lo, hi), optional
        Default :func:`default_bounds`.
    progress : callable, optional
        ``progress(evaluations, values, log_likelihood, best)`` after each evaluation.
    """
    start_time = time.perf_counter()
    if kind not in KINDS:
        raise ValueError(f"unknown kernel family {kind!r}; use one of {', '.join(KINDS)}")
    prepared = prepare_regression(Z, y, names) if _prepared is None else _prepared
    n = prepared[0].shape[0]
    Ts = float(Ts)
    if not (math.isfinite(Ts) and Ts > 0):
        raise ValueError(f"Ts must be a positive sample period in s, got {Ts!r}")
    periodic = kind in PERIODIC_KINDS
    if periodic:
        period = float(period) if period is not None else math.nan
        if not (math.isfinite(period) and period > 0):
            raise ValueError(f"period ψ must be a positive number of seconds, got {period!r}")
    spindle = kind == "spindle"
    span = None
    if spindle:
        if phase is None:
            raise ValueError("the spindle-phase kernel needs the stretches of constant spindle speed (phase)")
        period = 2.0 * math.pi if period is None else float(period)
        psi = phase.periods(period)
        psi = psi[np.isfinite(psi) & (phase.lengths > 1)]
        if psi.size == 0:
            raise ValueError("the spindle does not turn in this record: no spindle-phase kernel")
        span = (float(psi.max()), float(psi.min()))
    names_all = KINDS[kind] + ("gamma",)
    if bounds is None:
        bounds = default_bounds(kind, n, Ts, span if spindle else (period if periodic else None))
    bounds = dict(bounds)
    try:
        box = [(float(bounds[k][0]), float(bounds[k][1])) for k in names_all]
    except (KeyError, TypeError, IndexError):
        raise ValueError(f"bounds must give (lo, hi) for {', '.join(names_all)}; got {bounds!r}") from None
    if any(not (0 < lo < hi and math.isfinite(hi)) for lo, hi in box):
        raise ValueError(f"bounds must be (lo, hi) pairs with 0 < lo < hi for {', '.join(names_all)}; got {bounds!r}")
    lo_arr = np.log([b[0] for b in box])
    hi_arr = np.log([b[1] for b in box])
    state = {"evaluations": 0, "best": -math.inf, "best_x": None, "terms": None}

    def objective(theta) -> float:
        theta = np.clip(theta, lo_arr, hi_arr)
        vals = dict(zip(names_all, np.exp(theta).tolist()))
        try:
            terms = reml_terms(None, None, _make_kernel(kind, vals, period), vals["gamma"], Ts, segment=segment,
                               phase=phase if spindle else None, _prepared=prepared)
            ll = terms.log_likelihood
        except ValueError:
            terms, ll = None, -math.inf
        state["evaluations"] += 1
        if ll > state["best"]:
            state["best"], state["best_x"], state["terms"] = ll, np.array(theta), terms
        if progress is not None:
            progress(state["evaluations"], vals, ll, state["best"])
        return -ll if math.isfinite(ll) else 1e300

    starts = []
    if init:
        x0 = np.array([math.log(init[k]) if init.get(k) else 0.5 * (lo + hi)
                       for k, lo, hi in zip(names_all, lo_arr, hi_arr)])
        starts.append(np.clip(x0, lo_arr, hi_arr))
    levels = [(lo + 0.25 * (hi - lo), lo + 0.75 * (hi - lo)) for lo, hi in zip(lo_arr, hi_arr)]
    corners = itertools.product((0, 1), repeat=len(levels)) if design or not starts else ()
    for corner in corners:
        if len(levels) == 3 and sum(corner) % 2:  # half fraction 2^(3−1)
            continue
        starts.append(np.array([levels[i][c] for i, c in enumerate(corner)]))
    values = [objective(s) for s in starts]
    best = starts[int(np.argmin(values))]
    remaining = max_evaluations - state["evaluations"]
    if remaining >= 4:
        minimize(objective, best, method="Nelder-Mead", bounds=list(zip(lo_arr, hi_arr)),
                 options={"xatol": xatol, "fatol": fatol, "maxfev": remaining,
                          "initial_simplex": _simplex(best, lo_arr, hi_arr)})
    if state["best_x"] is None:
        raise ValueError("the likelihood could not be evaluated anywhere inside the bounds; check the data and bounds")
    best_vals = dict(zip(names_all, np.exp(state["best_x"]).tolist()))
    on_bound = {}
    for k, x, lo, hi in zip(names_all, state["best_x"], lo_arr, hi_arr):
        if x <= lo + BOUND_RTOL * (hi - lo):
            on_bound[k] = "lower"
        elif x >= hi - BOUND_RTOL * (hi - lo):
            on_bound[k] = "upper"
    gamma = best_vals.pop("gamma")
    return TuneResult(kind=kind, hyper=best_vals, gamma=gamma, log_likelihood=float(state["best"]),
                      evaluations=state["evaluations"], period=period if periodic or spindle else None,
                      seconds=time.perf_counter() - start_time, segment=n if segment is None else int(segment),
                      bounds=dict(zip(names_all, box)), on_bound=on_bound,
                      terms=state["terms"] if segment is None else None)


def _simplex(x0, lo, hi, step: float = 0.5):
    """Initial Nelder–Mead simplex: ±``step`` (log units) per coordinate, kept inside the bounds."""
    pts = [np.array(x0)]
    for i in range(len(x0)):
        p = np.array(x0)
        p[i] = p[i] + step if p[i] + step <= hi[i] else p[i] - step
        pts.append(p)
    return np.array(pts)
