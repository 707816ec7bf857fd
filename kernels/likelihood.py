"""Restricted marginal likelihood (REML) of the PL-LSSVM model, its tuning, and the evidence of a
candidate model (method §4).

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

GLS covariance of ``b`` (the uncertainty of β under the candidate):

    cov(b̂) = ŝ² (Z̃ᵀA⁻¹Z̃)⁻¹                                                                   (L3)

(``ŝ² (Z̃ᵀZ̃)⁻¹`` for LS).

Evidence of a candidate (:func:`log_evidence`): the REML at the tuned hyperparameters with a
Laplace/BIC-style penalty for the ``k`` hyperparameters fitted to the data,

    log E = ℓ(θ̂) − ½ k log(N − p)                                                                (L4)

(``s²`` is profiled in every candidate and not counted; hyperparameters given by the user, or kept
with ``--no-tune``, count 0; a period found from the data counts 1).

Evaluation (:func:`reml_terms`): by **whitening** with the inverse Cholesky factor of the Toeplitz
``A`` from one Levinson–Durbin pass (:func:`kernels.levinson.levinson_whiten`), which gives
``L⁻¹[Z̃, y]`` and ``log|A|`` together; then a QR of the whitened ``Z̃`` gives ``b̂``, ``yᵀPy``,
``log|Z̃ᵀA⁻¹Z̃|`` and (L3). Exact, ``O(N² (p + 2))`` time, ``O(N p)`` memory, independent of the
conditioning of ``A`` (long σ1 and large γ stall PCG, not Levinson). Long records use the order-m
approximation of :mod:`kernels.levinson` instead (``max_order``, ``tol``): the Durbin recursion
stopped at order m, later rows whitened by the order-m predictor (one FFT filter), ``O(m² (p + 2) +
N (p + 2) log m)`` — the exact likelihood of a nearby stationary process, so (L2) and (L3) keep their
meaning; m is chosen where the reflection coefficients show the lags beyond it to matter less than
``tol`` in log|A| (eq. V3), never before the kernel's support.

The spindle-phase kernel (:mod:`kernels.spindle_phase`, kind ``"spindle"``) on ``x = (t, θ)`` is
evaluated on the stretches of constant spindle speed (``phase``): block-diagonal ``A``, one exact
Levinson whitening per stretch with its own Toeplitz column (eq. S2), ``log|A| = Σ log|A_s|``.

Tuning (:func:`tune`) maximises the REML of the whole record, exact or of a given order.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import LinAlgError, cholesky, qr, solve_triangular
from scipy.optimize import minimize

from .blocks import blocks
from .covariance import Kernel, LocallyPeriodic, SquaredExponential, ZeroMeanLocallyPeriodic
from .levinson import levinson_whiten
from .pl_lssvm import _check_gamma, prepare_regression
from .spindle_phase import PhaseSegments, spindle_phase_kernel

__all__ = ["log_marginal_likelihood", "reml_terms", "REMLTerms", "log_evidence", "tune", "TuneResult",
           "default_bounds", "KINDS", "PERIODIC_KINDS", "BOUND_RTOL"]

#: kernel families that can be tuned: hyperparameter names besides γ
KINDS = {"squared_exponential": ("lengthscale",), "locally_periodic": ("sigma1", "sigma2"),
         "locally_periodic_zero_mean": ("sigma1", "sigma2"), "spindle": ("sigma1", "sigma2")}
#: the families with a period ψ
PERIODIC_KINDS = ("locally_periodic", "locally_periodic_zero_mean")
#: a tuned value within this fraction (in log space, of the bound interval) of a bound "ends on it"
BOUND_RTOL = 0.01
#: the order-m approximation is not stopped before the last lag where the kernel exceeds this share of k(0)
SUPPORT_RTOL = 1e-3


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
    order: int = 0  # order m of the approximation (n − 1: exact; 0: least squares)
    tail_estimate: float = 0.0  # what the lags beyond m would add to log|A| (eq. V3 of kernels.levinson)

    @property
    def beta(self) -> np.ndarray:
        return self.b[1:] if self.intercept else self.b

    @property
    def beta_cov(self) -> np.ndarray:
        return self.cov[1:, 1:] if self.intercept else self.cov


def _logdet_scaled_gram(Zs: np.ndarray) -> float:
    return 2.0 * float(np.sum(np.log(np.abs(np.diag(_r_factor(Zs))))))


#: the last few ``log|Z̃ᵀZ̃|`` (scaled) by regression: it does not change from one likelihood evaluation to the next
_GRAM_CACHE: dict = {}


def _gram_logdet(Zt: np.ndarray, scale: np.ndarray, kept) -> float:
    key = (id(Zt), Zt.shape, None if kept is None else hash(np.packbits(kept).tobytes()))
    hit = _GRAM_CACHE.get(key)
    if hit is not None and hit[0] is Zt:
        return hit[1]
    value = _logdet_scaled_gram((Zt if kept is None else Zt[kept]) / scale)
    if len(_GRAM_CACHE) >= 8:
        _GRAM_CACHE.pop(next(iter(_GRAM_CACHE)))
    _GRAM_CACHE[key] = (Zt, value)  # holds Zt: its id is not reused while cached
    return value


def reml_terms(Z, y, kernel: Kernel | None, gamma, Ts, *, names=None, max_order: int | None = None,
               tol: float = 0.0, phase: PhaseSegments | None = None, gate=None, keep=None,
               _prepared=None) -> REMLTerms:
    """All terms of the REML log likelihood (L2) and the GLS covariance (L3) on a uniform time grid.

    ``kernel=None`` is least squares (``A = I``; ``gamma`` ignored). Otherwise ``kernel`` must be a
    time kernel (``kernel.is_stationary_1d``) and ``Ts`` the sample period (s). Exact by default;
    ``max_order``/``tol`` select the order-m approximation of :mod:`kernels.levinson` (m at most
    ``max_order``, stopped earlier when the lags beyond it add less than ``tol`` to log|A| (V3), never
    before the kernel's support :func:`support_order`). With ``phase`` (the stretches of constant
    spindle speed), ``kernel`` is a kernel on ``(t, θ)`` (the spindle-phase kernel) evaluated
    block-diagonally; with ``gate`` (N,) bool the disturbance acts only where it is True (eq. B1 of
    :mod:`kernels.blocks`); with ``keep`` (N,) bool the samples where it is False are left out.
    """
    if _prepared is None:
        _prepared = prepare_regression(Z, y, names)
    Z_arr, y, names, Zt, intercept = _prepared
    n, p = Zt.shape
    scale = np.sqrt(np.sum(Zt * Zt, axis=0))
    kept = None if keep is None else np.asarray(keep, dtype=bool)
    if kernel is None:
        w = 1.0 if kept is None else kept[:, None]
        b, quad, logdet_M_s, Rinv = _qr_terms(Zt * w / scale, y * (1.0 if kept is None else kept))
        return _assemble(Zt, b / scale, quad, 0.0, logdet_M_s, Rinv, scale, "least-squares", intercept, kept=kept)
    gamma = _check_gamma(gamma)
    if phase is not None and phase.edges[-1] != n:
        raise ValueError(f"the spindle stretches cover {int(phase.edges[-1])} samples, the regression has {n}")
    if phase is None and not kernel.is_stationary_1d:
        raise ValueError(f"{kernel!r} is not a time kernel; the likelihood is implemented for uniform time grids")
    Ts = float(Ts)
    if not (math.isfinite(Ts) and Ts > 0):
        raise ValueError(f"Ts must be a positive sample period in s, got {Ts!r}")
    parts = blocks(kernel, gamma, Ts, n, gate=gate, phase=phase, max_order=max_order, keep=kept)
    white, logdet_A, order, tail = _whiten_blocks(np.column_stack([Zt, y]), parts, gamma, max_order, tol)
    if phase is not None:
        solver = f"spindle-{phase.count}"
    elif len(parts) > 1:
        solver = f"gated-{sum(b.column is not None for b in parts)}"
    else:
        solver = "levinson" if order >= n - 1 else f"levinson-ar{order}"
    b, quad, logdet_M_s, Rinv = _qr_terms(white[:, :p] / scale, white[:, p])
    return _assemble(Zt, b / scale, quad, logdet_A, logdet_M_s, Rinv, scale, solver, intercept, order, tail, kept)


def support_order(column, max_order: int) -> int:
    """The last lag (≤ ``max_order``) at which ``|column|`` exceeds :data:`SUPPORT_RTOL` of its peak: the
    order-m approximation is not stopped before it (a kernel that is ~0 between the multiples of a long
    period has no small reflection coefficient to show that a longer memory would not matter)."""
    head = np.abs(np.asarray(column[: max_order + 1]))
    big = np.flatnonzero(head > SUPPORT_RTOL * head[0])
    return int(big[-1]) if big.size else 0


def _whiten_blocks(data, parts, gamma, max_order, tol):
    """``L̃⁻¹ data`` block by block (eq. B1, V2), ``Σ log|Ã_s|``, the highest order used and the summed
    tail estimates (V3)."""
    white = np.empty_like(data)
    logdet, order, tail = 0.0, 0, 0.0
    for part in parts:
        a, b = part.start, part.stop
        if not part.kept:  # left out of the fit: carries nothing
            white[a:b] = 0.0
            continue
        if part.column is None:  # the gate is closed: white noise of variance 1/γ
            white[a:b] = data[a:b] * math.sqrt(gamma)
            logdet -= (b - a) * math.log(gamma)
            continue
        m_max = b - a - 1 if max_order is None else min(int(max_order), b - a - 1)
        res = levinson_whiten(part.column, data[a:b], max_order=max(m_max, 1) if b - a > 1 else None, tol=tol,
                              min_order=support_order(part.column, max(m_max, 0)))
        white[a:b] = res.white
        logdet += res.logdet
        order, tail = max(order, res.order), tail + res.tail_estimate
    return white, logdet, order, tail


def _r_factor(A: np.ndarray) -> np.ndarray:
    """The R factor (k × k) of the tall ``A`` (N × k): Cholesky-QR2 — two Gram products and one triangular
    solve, all BLAS-3 (Householder on a tall, thin matrix is memory-bound: 5× slower at N = 200 000) —
    falling back to Householder when the Gram matrix is too ill-conditioned for Cholesky."""
    try:
        R1 = cholesky(A.T @ A, lower=False, check_finite=False)
        Q = solve_triangular(R1, A.T, trans="T", lower=False, check_finite=False)  # (A R1⁻¹)ᵀ
        R2 = cholesky(Q @ Q.T, lower=False, check_finite=False)
        R = R2 @ R1
        if np.all(np.isfinite(R)):
            return R
    except LinAlgError:
        pass
    return qr(A, mode="economic", check_finite=False)[1]


def _qr_terms(Zw: np.ndarray, yw: np.ndarray):
    """GLS on whitened, column-scaled data: ``b_s``, ``yᵀPy``, ``log|Z_wᵀZ_w|`` and ``R⁻¹``, from the R factor
    of ``[Z_w, y_w]`` alone (Q never formed: ``R = [[R₁₁, r], [0, ρ]]``, ``b = R₁₁⁻¹r``, ``yᵀPy = ρ²``)."""
    p = Zw.shape[1]
    R = _r_factor(np.column_stack([Zw, yw]))
    R11 = R[:p, :p]
    bs = solve_triangular(R11, R[:p, p], check_finite=False)
    logdet = 2.0 * float(np.sum(np.log(np.abs(np.diag(R11)))))
    Rinv = solve_triangular(R11, np.eye(p), check_finite=False)
    return bs, float(R[p, p] ** 2) if R.shape[0] > p else 0.0, logdet, Rinv


def _assemble(Zt, b, quad, logdet_A, logdet_M_scaled, Rinv, scale, solver, intercept, order=0,
              tail=0.0, kept=None) -> REMLTerms:
    n, p = Zt.shape if kept is None else (int(np.sum(kept)), Zt.shape[1])
    if not quad > 0:
        raise ValueError("yᵀPy is not positive: the data are fitted exactly; the likelihood is undefined")
    logdet_ZZ_scaled = _gram_logdet(Zt, scale, kept)
    two_log_scale = 2.0 * float(np.sum(np.log(scale)))
    dof = n - p
    s2 = quad / dof
    ll = -0.5 * (dof * (math.log(2.0 * math.pi * s2) + 1.0) + logdet_A + logdet_M_scaled - logdet_ZZ_scaled)
    cov = s2 * (Rinv @ Rinv.T) / np.outer(scale, scale)
    return REMLTerms(log_likelihood=ll, s2=s2, logdet_A=logdet_A, logdet_M=logdet_M_scaled - two_log_scale,
                     logdet_ZZ=logdet_ZZ_scaled + two_log_scale, quad=quad, n=n, p=p, b=b,
                     cov=0.5 * (cov + cov.T), solver=solver, intercept=bool(intercept), order=int(order),
                     tail_estimate=float(tail))


def log_marginal_likelihood(Z, y, kernel, gamma, Ts, *, names=None, max_order: int | None = None,
                            tol: float = 0.0) -> float:
    """Restricted log marginal likelihood (L2) of the PL-LSSVM model with ``kernel`` and ``gamma``
    on a uniform grid of period ``Ts`` (``kernel=None``: least squares). Exact by default;
    ``max_order``/``tol``: the order-m approximation (:func:`reml_terms`)."""
    return reml_terms(Z, y, kernel, gamma, Ts, names=names, max_order=max_order, tol=tol).log_likelihood


def log_evidence(log_likelihood: float, k: int, n: int, p: int) -> float:
    """(L4): ``ℓ − ½ k log(N − p)`` for ``k`` hyperparameters fitted to the data."""
    return float(log_likelihood) - 0.5 * int(k) * math.log(max(n - p, 2))


def default_bounds(kind: str, n: int, Ts: float, period: float | None = None) -> dict:
    """Hyperparameter bounds scaled to the record, ``T = N Ts`` the record length.

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
    log_likelihood: float  # the tuning objective at the optimum (the REML at the order used)
    evaluations: int
    period: float | None = None  # ψ (s); for "spindle" the angle period P (rad)
    seconds: float = 0.0
    order: int = 0  # the highest order m of the approximation used at the optimum (n − 1: exact)
    bounds: dict = field(default_factory=dict)
    on_bound: dict = field(default_factory=dict)  # name → "lower" | "upper"
    terms: REMLTerms | None = None  # REML terms at the optimum

    def kernel(self) -> Kernel:
        return _make_kernel(self.kind, self.hyper, self.period)

    @property
    def sigma1(self) -> float | None:
        return self.hyper.get("sigma1")

    @property
    def sigma2(self) -> float | None:
        return self.hyper.get("sigma2")


def tune(Z, y, Ts, period=None, *, kind: str = "locally_periodic", init: dict | None = None,
         bounds: dict | None = None, progress=None, names=None, max_order: int | None = None, tol: float = 0.0,
         max_evaluations: int = 30, xatol: float = 0.1, fatol: float = 0.1, design: bool = True,
         step: float = 0.5, phase: PhaseSegments | None = None, gate=None, keep=None,
         _prepared=None) -> TuneResult:
    """Maximise the REML (L2) over the log hyperparameters of ``kind`` and log γ.

    The objective is the REML of the whole record, exact or of order ≤ ``max_order`` (``tol``:
    :func:`reml_terms`). Several starts: ``init`` (clipped into the bounds) and, with ``design``, a two-level design at ¼
    and ¾ of each log range (the 4 corners in 2-D, a half fraction of the 8 corners in 3-D); bounded
    Nelder–Mead from the best start (initial simplex ±``step`` in log units, ``xatol`` in log units,
    ``fatol`` in log likelihood) until ``max_evaluations``.
    ``on_bound`` names the values that end within ``BOUND_RTOL`` of a bound (in log space).

    Parameters
    ----------
    Z, y : regression data (method §2); ``Ts`` sample period (s); ``period`` ψ (s) for the locally
        periodic kernel; for ``"spindle"`` the angle period P (rad, default 2π: per revolution).
    kind : "locally_periodic", "locally_periodic_zero_mean", "squared_exponential" or "spindle"
        (the spindle-phase kernel on the stretches ``phase`` of constant spindle speed)
    gate, keep : arrays (N,) of bool, optional
        Where the disturbance acts (eq. B1 of :mod:`kernels.blocks`); the samples in the fit.
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
            terms = reml_terms(None, None, _make_kernel(kind, vals, period), vals["gamma"], Ts, max_order=max_order,
                               tol=tol, phase=phase if spindle else None, gate=gate, keep=keep, _prepared=prepared)
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
                          "initial_simplex": _simplex(best, lo_arr, hi_arr, step)})
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
                      seconds=time.perf_counter() - start_time, order=state["terms"].order,
                      bounds=dict(zip(names_all, box)), on_bound=on_bound,
                      terms=state["terms"])


def _simplex(x0, lo, hi, step: float = 0.5):
    """Initial Nelder–Mead simplex: ±``step`` (log units) per coordinate, kept inside the bounds."""
    pts = [np.array(x0)]
    for i in range(len(x0)):
        p = np.array(x0)
        p[i] = p[i] + step if p[i] + step <= hi[i] else p[i] - step
        pts.append(p)
    return np.array(pts)
