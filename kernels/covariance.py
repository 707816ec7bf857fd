"""Covariance functions: one definition each, shared by the batch and online paths.

Every kernel is a product of *factors*. A factor has a kind, up to three
parameters and the slice of input columns it reads. The same factor table
drives

* the vectorised NumPy evaluation ``kernel(X1, X2)`` used by PL-LSSVM and tests,
* the stationary lag function ``kernel.lag(d)`` used by the Toeplitz solver,
* the ``@njit`` row evaluations :func:`kernel_row` and :func:`kernel_row_phased` (the
  KRLS-T step: one ``exp`` per entry, the periodic terms from cached phases),

so there is exactly one formula per kernel (method §5).

Conventions (method §5, thesis eq. 2.11 corrected), ``d = x - x'``:

* squared exponential      ``k = exp(-||d||² / (2 ℓ²))``
* periodic                 ``k = exp(-sin²(π d / ψ) / (2 σ2²))``   (thesis σ2;
  scikit-learn's ExpSineSquared length scale is ``2 σ2``)
* locally periodic         ``k = exp(-d² / (2 σ1²)) · exp(-sin²(π d / ψ) / (2 σ2²))``

All kernels have ``k(x, x) = 1``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

__all__ = [
    "Kernel",
    "SquaredExponential",
    "Periodic",
    "LocallyPeriodic",
    "ZeroMeanLocallyPeriodic",
    "Product",
    "KIND_SE",
    "KERNEL_FLOOR",
    "KIND_PERIODIC",
    "KIND_LOCALLY_PERIODIC",
    "kernel_value",
    "envelope_bound",
    "kernel_value_at",
    "kernel_row",
    "kernel_row_at",
    "kernel_phases",
    "kernel_row_phased",
]

KIND_SE = 0
KIND_PERIODIC = 1
KIND_LOCALLY_PERIODIC = 2
KIND_LOCALLY_PERIODIC_ZERO_MEAN = 3
#: the online tracker's kernel values of magnitude below 2⁻⁵¹¹ (≈ 1.5e-154, the square root of the smallest
#: normal double) are 0: 148 orders of magnitude below the jitter, and the products of two of them in the
#: rank-one updates would otherwise be subnormal numbers, which x86 processes ~100× slower
KERNEL_FLOOR = 2.0 ** -511


@dataclass(frozen=True)
class Factor:
    """One factor of a product kernel: ``kind``, ``params`` (3 floats) and columns ``[start, stop)``.

    ``stop = -1`` means "to the last column".
    """

    kind: int
    params: tuple[float, float, float]
    start: int = 0
    stop: int = -1


def _check_positive(name: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value) or value <= 0.0:
        raise ValueError(f"kernel parameter {name} must be a positive finite number, got {value!r}")
    return value


def _dims_to_range(dims) -> tuple[int, int]:
    if dims is None:
        return 0, -1
    if isinstance(dims, slice):
        if dims.step not in (None, 1):
            raise ValueError("kernel dims must be a contiguous slice (step 1)")
        start = 0 if dims.start is None else int(dims.start)
        stop = -1 if dims.stop is None else int(dims.stop)
        if start < 0 or (stop != -1 and stop <= start):
            raise ValueError(f"kernel dims {dims} select no columns")
        return start, stop
    index = int(dims)
    if index < 0:
        raise ValueError("kernel dims must be a non-negative column index or a slice")
    return index, index + 1


def _as_2d(X) -> np.ndarray:
    X = np.asarray(X, dtype=np.float64)
    if X.ndim == 0:
        return X.reshape(1, 1)
    if X.ndim == 1:
        return X.reshape(-1, 1)
    if X.ndim != 2:
        raise ValueError(f"kernel inputs must be scalars, 1-D or 2-D arrays, got shape {X.shape}")
    return X


def _factor_matrix(f: Factor, X1: np.ndarray, X2: np.ndarray) -> np.ndarray:
    stop = X1.shape[1] if f.stop == -1 else f.stop
    A = X1[:, f.start:stop]
    B = X2[:, f.start:stop]
    if A.shape[1] == 0:
        raise ValueError(f"kernel factor reads columns [{f.start}, {stop}) but inputs have {X1.shape[1]}")
    if f.kind == KIND_SE:
        sq = np.sum(A * A, 1)[:, None] + np.sum(B * B, 1)[None, :] - 2.0 * (A @ B.T)
        np.maximum(sq, 0.0, out=sq)
        return _se_formula(sq, f.params[0])
    if A.shape[1] != 1:
        raise ValueError("periodic and locally periodic factors act on one scalar column (time)")
    d = A[:, 0][:, None] - B[:, 0][None, :]
    return _lag_values(f, d)


def _se_formula(sq, ell):
    """Squared exponential factor from the squared distance ``sq``."""
    return np.exp(-sq / (2.0 * ell * ell))


def _periodic_formula(d, sigma2, period):
    """Periodic factor at lag ``d`` (thesis σ2)."""
    s = np.sin(np.pi * d / period)
    return np.exp(-(s * s) / (2.0 * sigma2 * sigma2))


def _locally_periodic_formula(d, sigma1, sigma2, period):
    """Locally periodic factor at lag ``d`` (method §5)."""
    s = np.sin(np.pi * d / period)
    return np.exp(-(d * d) / (2.0 * sigma1 * sigma1) - (s * s) / (2.0 * sigma2 * sigma2))


def _i0e(a):
    """``e^(−a) I0(a)`` for ``a ≥ 0`` (modified Bessel function, exponentially scaled) by its power
    series ``Σ_k e^(−a) (a/2)^(2k)/(k!)²``, summed until the terms no longer change the sum (a ≤ 100
    in use: at most a few hundred terms, all positive, so the sum is accurate to rounding)."""
    term = math.exp(-a)
    total = term
    q = 0.25 * a * a
    k = 0
    while True:
        k += 1
        term *= q / (k * k)
        if total + term == total:
            return total
        total += term


def _locally_periodic_zero_mean_formula(d, sigma1, sigma2, period):
    """Zero-mean locally periodic factor at lag ``d``: ``exp(−d²/(2σ1²)) · (p(d) − c0)/(1 − c0)`` with the
    periodic factor ``p`` and its mean over a period ``c0 = e^(−a) I0(a)``, ``a = 1/(4σ2²)``."""
    s = np.sin(np.pi * d / period)
    c0 = _i0e(1.0 / (4.0 * sigma2 * sigma2))
    return np.exp(-(d * d) / (2.0 * sigma1 * sigma1)) * (np.exp(-(s * s) / (2.0 * sigma2 * sigma2)) - c0) / (1.0 - c0)


def _lag_values(f: Factor, d: np.ndarray) -> np.ndarray:
    """k(d) of one stationary scalar factor (eq. of method §5)."""
    if f.kind == KIND_SE:
        return _se_formula(d * d, f.params[0])
    if f.kind == KIND_PERIODIC:
        return _periodic_formula(d, f.params[0], f.params[1])
    if f.kind == KIND_LOCALLY_PERIODIC:
        return _locally_periodic_formula(d, *f.params)
    if f.kind == KIND_LOCALLY_PERIODIC_ZERO_MEAN:
        return _locally_periodic_zero_mean_formula(d, *f.params)
    raise ValueError(f"unknown kernel kind {f.kind}")


class Kernel:
    """Base class: a product of :class:`Factor` s. Subclasses only build the factor table."""

    factors: tuple[Factor, ...] = ()

    # -- evaluation -----------------------------------------------------------
    def __call__(self, X1, X2=None) -> np.ndarray:
        """Kernel matrix ``K[i, j] = k(X1[i], X2[j])`` (``X2 = X1`` when omitted)."""
        A = _as_2d(X1)
        B = A if X2 is None else _as_2d(X2)
        if A.shape[1] != B.shape[1]:
            raise ValueError(f"kernel inputs disagree in dimension: {A.shape[1]} vs {B.shape[1]}")
        K = np.ones((A.shape[0], B.shape[0]))
        for f in self.factors:
            K *= _factor_matrix(f, A, B)
        return K

    def diag(self, X) -> np.ndarray:
        """``k(x, x)`` for each row: all kernels here are normalised to 1."""
        return np.ones(_as_2d(X).shape[0])

    @property
    def is_stationary_1d(self) -> bool:
        """True when ``k`` is a function of the lag of one scalar input (a time kernel)."""
        return all(f.start == 0 and f.stop in (-1, 1) for f in self.factors)

    def lag(self, d) -> np.ndarray:
        """``k(d)`` for a scalar time kernel, ``d = t - t'`` (first column of a Toeplitz matrix)."""
        if not self.is_stationary_1d:
            raise ValueError(f"{self!r} is not a function of a scalar lag; use kernel(X1, X2)")
        d = np.asarray(d, dtype=np.float64)
        out = np.ones_like(d)
        for f in self.factors:
            out = out * _lag_values(f, d)
        return out

    # -- numba table ------------------------------------------------------------
    def spec(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Arrays ``(kinds int64[F], params float64[F,3], cols int64[F,2])`` for :func:`kernel_row`."""
        kinds = np.array([f.kind for f in self.factors], dtype=np.int64)
        params = np.array([f.params for f in self.factors], dtype=np.float64).reshape(-1, 3)
        cols = np.array([(f.start, f.stop) for f in self.factors], dtype=np.int64).reshape(-1, 2)
        return kinds, params, cols

    # -- composition and description ------------------------------------------------
    def __mul__(self, other: Kernel) -> Product:
        if not isinstance(other, Kernel):
            return NotImplemented
        return Product(self, other)

    def to_dict(self) -> dict:
        """Plain description, for model files and snapshots."""
        raise NotImplementedError

    @staticmethod
    def from_dict(d: dict) -> Kernel:
        """Inverse of :meth:`to_dict`; raises ``ValueError`` naming the bad key."""
        if not isinstance(d, dict) or "type" not in d:
            raise ValueError("kernel description needs a 'type' key")
        kind = d["type"]
        dims = d.get("dims")
        if isinstance(dims, list):
            dims = slice(int(dims[0]), None if int(dims[1]) == -1 else int(dims[1]))
        try:
            if kind == "locally_periodic":
                return LocallyPeriodic(d["sigma1"], d["sigma2"], d["period"], dims=dims)
            if kind == "periodic":
                return Periodic(d["sigma2"], d["period"], dims=dims)
            if kind == "squared_exponential":
                return SquaredExponential(d["lengthscale"], dims=dims)
            if kind == "product":
                return Product(*[Kernel.from_dict(x) for x in d["factors"]])
            if kind == "locally_periodic_zero_mean":
                return ZeroMeanLocallyPeriodic(d["sigma1"], d["sigma2"], d["period"], dims=dims)
        except KeyError as exc:
            raise ValueError(f"kernel of type {kind!r} is missing key {exc.args[0]!r}") from None
        raise ValueError(
            f"unknown kernel type {kind!r}; use locally_periodic, locally_periodic_zero_mean, periodic, "
            "squared_exponential or product"
        )

    def _dims_dict(self, f: Factor) -> dict:
        return {} if (f.start, f.stop) == (0, -1) else {"dims": [f.start, f.stop]}

    def __eq__(self, other) -> bool:
        return isinstance(other, Kernel) and self.factors == other.factors

    def __hash__(self) -> int:
        return hash(self.factors)


class SquaredExponential(Kernel):
    """RBF kernel ``k(x, x') = exp(-||x - x'||² / (2 ℓ²))`` on vector inputs.

    Parameters
    ----------
    lengthscale : float
        ℓ, in the units of the inputs.
    dims : int or slice, optional
        Input columns the kernel reads (all by default).
    """

    def __init__(self, lengthscale: float, dims=None):
        self.lengthscale = _check_positive("lengthscale", lengthscale)
        start, stop = _dims_to_range(dims)
        self.factors = (Factor(KIND_SE, (self.lengthscale, 0.0, 0.0), start, stop),)

    def to_dict(self) -> dict:
        return {"type": "squared_exponential", "lengthscale": self.lengthscale, **self._dims_dict(self.factors[0])}

    def __repr__(self) -> str:
        return f"SquaredExponential(lengthscale={self.lengthscale!r})"


class Periodic(Kernel):
    """Periodic kernel ``k(d) = exp(-sin²(π d / ψ) / (2 σ2²))`` on a scalar input (method §5).

    Parameters
    ----------
    sigma2 : float
        σ2, thesis convention (scikit-learn's ExpSineSquared uses ``ℓ = 2 σ2``).
    period : float
        ψ, the disturbance period in the input's units (s for time).
    """

    def __init__(self, sigma2: float, period: float, dims=None):
        self.sigma2 = _check_positive("sigma2", sigma2)
        self.period = _check_positive("period", period)
        start, stop = _dims_to_range(dims)
        self.factors = (Factor(KIND_PERIODIC, (self.sigma2, self.period, 0.0), start, stop),)

    def to_dict(self) -> dict:
        return {"type": "periodic", "sigma2": self.sigma2, "period": self.period, **self._dims_dict(self.factors[0])}

    def __repr__(self) -> str:
        return f"Periodic(sigma2={self.sigma2!r}, period={self.period!r})"


class LocallyPeriodic(Kernel):
    """Locally periodic kernel on time (thesis eq. 2.11 as corrected in method §5).

    ``k(d) = exp(-d² / (2 σ1²)) · exp(-sin²(π d / ψ) / (2 σ2²))``, ``d = t - t'``.

    Parameters
    ----------
    sigma1 : float
        σ1 (s), how long the periodic pattern stays correlated.
    sigma2 : float
        σ2, smoothness within one period (thesis convention).
    period : float
        ψ (s): 1/55 s for the shaker, 60/rpm for a spindle with runout.
    """

    def __init__(self, sigma1: float, sigma2: float, period: float, dims=None):
        self.sigma1 = _check_positive("sigma1", sigma1)
        self.sigma2 = _check_positive("sigma2", sigma2)
        self.period = _check_positive("period", period)
        start, stop = _dims_to_range(dims)
        self.factors = (
            Factor(KIND_LOCALLY_PERIODIC, (self.sigma1, self.sigma2, self.period), start, stop),
        )

    def to_dict(self) -> dict:
        return {
            "type": "locally_periodic",
            "sigma1": self.sigma1,
            "sigma2": self.sigma2,
            "period": self.period,
            **self._dims_dict(self.factors[0]),
        }

    def __repr__(self) -> str:
        return f"LocallyPeriodic(sigma1={self.sigma1!r}, sigma2={self.sigma2!r}, period={self.period!r})"


class ZeroMeanLocallyPeriodic(Kernel):
    """Locally periodic kernel whose periodic factor has its mean (constant Fourier term) removed.

    ``k(d) = exp(−d²/(2σ1²)) · (p(d) − c0) / (1 − c0)``, ``p(d) = exp(−sin²(πd/ψ)/(2σ2²))``,
    ``c0 = e^(−a) I0(a)``, ``a = 1/(4σ2²)`` (``p = e^(−a) Σ_j ε_j I_j(a) cos(2πjd/ψ)``, so ``c0`` is its
    ``j = 0`` term); ``k(0) = 1``. Positive definite: the remaining Fourier weights are positive and
    the product with the squared exponential keeps that. As σ2 → ∞ it tends to
    ``exp(−d²/(2σ1²)) cos(2πd/ψ)``. The plain locally periodic kernel (method §5) carries a
    slowly varying mean with weight ``c0`` (most of its variance for σ2 ≳ 1): right for a cutting
    force whose mean follows the feed, but a zero-mean disturbance (a shaker) is then modelled with a
    slow drift that competes with the velocity regressor — offline in PL-LSSVM and online, where a
    tracker with that slow part takes up friction and damping that online β should see. One factor
    of the table (kind ``KIND_LOCALLY_PERIODIC_ZERO_MEAN``), so the batch, Toeplitz and compiled paths
    share its formula (:func:`_locally_periodic_zero_mean_formula`).
    """

    def __init__(self, sigma1: float, sigma2: float, period: float, dims=None):
        self.sigma1 = _check_positive("sigma1", sigma1)
        self.sigma2 = _check_positive("sigma2", sigma2)
        self.period = _check_positive("period", period)
        self.c0 = _i0e(1.0 / (4.0 * self.sigma2 * self.sigma2))
        start, stop = _dims_to_range(dims)
        self.factors = (Factor(KIND_LOCALLY_PERIODIC_ZERO_MEAN, (self.sigma1, self.sigma2, self.period), start, stop),)

    def to_dict(self) -> dict:
        return {"type": "locally_periodic_zero_mean", "sigma1": self.sigma1, "sigma2": self.sigma2,
                "period": self.period, **self._dims_dict(self.factors[0])}

    def __repr__(self) -> str:
        return f"ZeroMeanLocallyPeriodic(sigma1={self.sigma1!r}, sigma2={self.sigma2!r}, period={self.period!r})"


class Product(Kernel):
    """Product of kernels, ``k = k_a · k_b · …`` (positive definite when each factor is)."""

    def __init__(self, *kernels: Kernel):
        if len(kernels) < 2:
            raise ValueError("Product needs at least two kernels")
        self.kernels = tuple(kernels)
        self.factors = tuple(f for k in kernels for f in k.factors)

    def to_dict(self) -> dict:
        return {"type": "product", "factors": [k.to_dict() for k in self.kernels]}

    def __repr__(self) -> str:
        return " * ".join(repr(k) for k in self.kernels)


# ---------------------------------------------------------------------------
# @njit evaluation (online path).
#
# The three factor formulas below are the only place the kernels are written down:
# ``_lag_values``/``_factor_matrix`` call the plain Python functions with NumPy
# arrays, the ``@njit`` code calls their compiled twins (``_se``, ``_periodic``,
# ``_locally_periodic``) with scalars.
#
# The compiled evaluation takes the *index* of a row and of a factor
# (``X, i`` and ``params, f``) instead of the views ``X[i]`` and ``params[f]``:
# creating an array view inside a hot loop costs a reference-count round trip
# and blocks inlining (about 3x the cost of the formula itself).
# ---------------------------------------------------------------------------

_se = njit(cache=True, nogil=True)(_se_formula)
_periodic = njit(cache=True, nogil=True)(_periodic_formula)
_locally_periodic = njit(cache=True, nogil=True)(_locally_periodic_formula)
_i0e_nb = njit(cache=True, nogil=True)(_i0e)


@njit(cache=True, nogil=True)
def _locally_periodic_zero_mean(d, sigma1, sigma2, period):
    """Compiled twin of :func:`_locally_periodic_zero_mean_formula` (the same expression)."""
    s = math.sin(math.pi * d / period)
    c0 = _i0e_nb(1.0 / (4.0 * sigma2 * sigma2))
    return math.exp(-(d * d) / (2.0 * sigma1 * sigma1)) * (math.exp(-(s * s) / (2.0 * sigma2 * sigma2)) - c0) / (1.0 - c0)


@njit(cache=True, nogil=True)
def _factor(kind, params, f, r):
    """Factor ``f`` of the table at ``r``: the squared distance (SE) or the signed lag (others)."""
    if kind == KIND_SE:
        return _se(r, params[f, 0])
    if kind == KIND_PERIODIC:
        return _periodic(r, params[f, 0], params[f, 1])
    if kind == KIND_LOCALLY_PERIODIC_ZERO_MEAN:
        return _locally_periodic_zero_mean(r, params[f, 0], params[f, 1], params[f, 2])
    return _locally_periodic(r, params[f, 0], params[f, 1], params[f, 2])


@njit(cache=True, nogil=True)
def kernel_value_at(kinds, params, cols, X, i, x):
    """``k(X[i], x)`` for the factor table from :meth:`Kernel.spec` (X: 2-D, x: 1-D float64).

    The same value as ``kernel_value(kinds, params, cols, X[i], x)`` without the view ``X[i]``.
    """
    v = 1.0
    for f in range(kinds.shape[0]):
        kind = kinds[f]
        start = cols[f, 0]
        stop = cols[f, 1]
        if stop == -1:
            stop = x.shape[0]
        if kind == KIND_SE:
            r = 0.0
            for j in range(start, stop):
                d = X[i, j] - x[j]
                r += d * d
        else:
            r = X[i, start] - x[start]
        v *= _factor(kind, params, f, r)
    return v


@njit(cache=True, nogil=True)
def envelope_bound(kinds, params):
    """``(σ, B)`` with ``|k(d)| ≤ B·exp(−d²/(2σ²))`` for a time kernel: σ the narrowest squared-exponential
    envelope (SE, locally periodic, zero-mean locally periodic factors; ``inf`` when none decays) and
    ``B`` the product of the factors' largest magnitudes (1, or ``max(1, c0/(1 − c0))`` for a zero-mean
    factor, whose ``(p − c0)/(1 − c0)`` lies in ``[−c0/(1 − c0), 1]``)."""
    sigma = math.inf
    bound = 1.0
    for f in range(kinds.shape[0]):
        kind = kinds[f]
        if kind == KIND_SE or kind == KIND_LOCALLY_PERIODIC or kind == KIND_LOCALLY_PERIODIC_ZERO_MEAN:
            sigma = min(sigma, params[f, 0])
        if kind == KIND_LOCALLY_PERIODIC_ZERO_MEAN:
            c0 = _i0e_nb(1.0 / (4.0 * params[f, 1] * params[f, 1]))
            bound *= max(1.0, c0 / (1.0 - c0))
    return sigma, bound


@njit(cache=True, nogil=True)
def kernel_value(kinds, params, cols, x1, x2):
    """``k(x1, x2)`` for the factor table from :meth:`Kernel.spec` (x1, x2: 1-D float64).

    :func:`kernel_value_at` on a one-row view of ``x1`` (same arithmetic, same bits).
    """
    return kernel_value_at(kinds, params, cols, x1.reshape((1, x1.shape[0])), np.int64(0), x2)


_ALL_ROWS = np.zeros(0, dtype=np.int64)


@njit(cache=True, nogil=True)
def _rows(kinds, params, cols, X, idx, use_idx, n, x, out):
    """``out[i] = k(X[i], x)`` for ``i = idx[l]`` (or ``i = l``), ``l < n``: factor-outer loops.

    Each factor's parameters are hoisted and its formula runs over all rows in one
    tight loop; per row this is the product ``((1·f0)·f1)·…`` of :func:`kernel_value_at`,
    so both give the same bits.
    """
    for l in range(n):
        i = idx[l] if use_idx else l
        out[i] = 1.0
    for f in range(kinds.shape[0]):
        kind = kinds[f]
        start = cols[f, 0]
        stop = cols[f, 1]
        if stop == -1:
            stop = x.shape[0]
        p0 = params[f, 0]
        p1 = params[f, 1]
        p2 = params[f, 2]
        x0 = x[start]
        if kind == KIND_SE:
            for l in range(n):
                i = idx[l] if use_idx else l
                r = 0.0
                for j in range(start, stop):
                    d = X[i, j] - x[j]
                    r += d * d
                out[i] *= _se(r, p0)
        elif kind == KIND_PERIODIC:
            for l in range(n):
                i = idx[l] if use_idx else l
                out[i] *= _periodic(X[i, start] - x0, p0, p1)
        else:
            for l in range(n):
                i = idx[l] if use_idx else l
                out[i] *= _locally_periodic(X[i, start] - x0, p0, p1, p2)


@njit(cache=True, nogil=True)
def kernel_row(kinds, params, cols, X, n, x, out):
    """``out[i] = k(X[i], x)`` for ``i < n`` without allocation (the KRLS-T ``k_t``)."""
    _rows(kinds, params, cols, X, _ALL_ROWS, False, n, x, out)


@njit(cache=True, nogil=True)
def kernel_row_at(kinds, params, cols, X, idx, n, x, out):
    """``out[idx[l]] = k(X[idx[l]], x)`` for ``l < n`` (rows picked by an index list, e.g. slots)."""
    _rows(kinds, params, cols, X, idx, True, n, x, out)


# ---------------------------------------------------------------------------
# Row evaluation with cached phases (the KRLS-T step).
#
# Every factor is exp(−E) with E ≥ 0, so a row needs one ``exp`` per entry of
# the sum of the factors' E (the same products as above, up to rounding). For a
# periodic term sin(π(x − x')/ψ) = sin a cos a' − cos a sin a' with
# a = π·fmod(x, ψ)/ψ: fmod is exact and ψ-periodic, so the identity holds for
# any magnitude of x (a time stamp of days, a cumulative spindle angle) and the
# sines and cosines of small arguments are accurate to rounding. Each input's
# (sin a, cos a) per periodic factor is computed once (:func:`kernel_phases`)
# and kept with it; a row then costs multiplications and one exp per entry.
# That exp is written out (:func:`_exp_nonpositive`) so that the row loops
# vectorise (libm's exp is a call per entry: ~4 ns against ~1 ns).
# ---------------------------------------------------------------------------


@intrinsic
def _double_from_bits(typingctx, bits):
    """The float64 whose IEEE-754 bit pattern is the int64 ``bits``."""
    sig = types.float64(types.int64)

    def codegen(context, builder, sig, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return sig, codegen


_LOG2E = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01     # ln 2 in two parts: k·_LN2_HI is exact for |k| < 2^11
_LN2_LO = 1.90821492927058770002e-10


@njit(cache=True, nogil=True, inline="always")
def _exp_nonpositive(x):
    """``exp(x)`` for ``x ≤ 0`` (0 below −708), within 1 ulp of libm, without calls or branches.

    ``exp(x) = 2^k · exp(r)``, ``k = round(x/ln 2)``, ``|r| ≤ ln(2)/2``; ``exp(r)`` by its Taylor
    polynomial of degree 13 (truncation < 2e-16 relative), ``2^k`` from the exponent bits.
    """
    xc = max(x, -708.0)
    k = np.floor(xc * _LOG2E + 0.5)
    r = (xc - k * _LN2_HI) - k * _LN2_LO
    p = 1.0 / 6227020800.0
    p = p * r + 1.0 / 479001600.0
    p = p * r + 1.0 / 39916800.0
    p = p * r + 1.0 / 3628800.0
    p = p * r + 1.0 / 362880.0
    p = p * r + 1.0 / 40320.0
    p = p * r + 1.0 / 5040.0
    p = p * r + 1.0 / 720.0
    p = p * r + 1.0 / 120.0
    p = p * r + 1.0 / 24.0
    p = p * r + 1.0 / 6.0
    p = p * r + 0.5
    p = p * r + 1.0
    p = p * r + 1.0
    v = p * _double_from_bits((np.int64(k) + 1023) << 52)
    return v if x >= -708.0 else 0.0


@njit(cache=True, nogil=True)
def _period(kinds, params, f):
    """ψ of factor ``f`` (0 for a squared exponential)."""
    if kinds[f] == KIND_PERIODIC:
        return params[f, 1]
    if kinds[f] == KIND_LOCALLY_PERIODIC or kinds[f] == KIND_LOCALLY_PERIODIC_ZERO_MEAN:
        return params[f, 2]
    return 0.0


@njit(cache=True, nogil=True)
def kernel_phases(kinds, params, cols, x, out):
    """``out[2f], out[2f+1] = sin a_f, cos a_f`` with ``a_f = π·fmod(x_c, ψ_f)/ψ_f`` (``fmod`` is exact) for each
    periodic or locally periodic factor ``f`` on column ``c`` (0, 0 for a squared exponential)."""
    for f in range(kinds.shape[0]):
        psi = _period(kinds, params, f)
        if psi > 0.0:
            a = math.pi * (np.fmod(x[cols[f, 0]], psi) / psi)
            out[2 * f] = math.sin(a)
            out[2 * f + 1] = math.cos(a)
        else:
            out[2 * f] = 0.0
            out[2 * f + 1] = 0.0


@njit(cache=True, nogil=True)
def kernel_row_phased(kinds, params, cols, X, Ph, w, lo, hi, x, xph, out):
    """``out[i] = w[i]·k(X[i], x)`` for ``lo ≤ i < hi`` (the KRLS-T ``k_t`` over slots; ``w``: 1 for
    an occupied slot, 0 for a free one); a value of magnitude below :data:`KERNEL_FLOOR` is 0.

    ``Ph[i]`` and ``xph`` are :func:`kernel_phases` of ``X[i]`` and ``x``. The exponent is summed
    factor by factor (each factor's loop runs over all rows), then one ``exp`` per entry
    (:func:`_exp_nonpositive`):
    squared exponential ``−‖d‖²/(2ℓ²)``, periodic ``−s²/(2σ2²)`` with ``s = sin(π d/ψ)`` from the
    phases, locally periodic both (``d = x − x'``, method §5).
    """
    for i in range(lo, hi):
        out[i] = 0.0
    for f in range(kinds.shape[0]):
        kind = kinds[f]
        start = cols[f, 0]
        stop = cols[f, 1]
        if stop == -1:
            stop = x.shape[0]
        if kind == KIND_SE:
            c1 = 1.0 / (2.0 * params[f, 0] * params[f, 0])
            if stop == start + 1:                                  # one column: a loop that vectorises
                x0 = x[start]
                for i in range(lo, hi):
                    d = X[i, start] - x0
                    out[i] -= (d * d) * c1                         # −d²/(2ℓ²)
                continue
            for i in range(lo, hi):
                r = 0.0
                for j in range(start, stop):
                    d = X[i, j] - x[j]
                    r += d * d
                out[i] -= r * c1                                   # −‖d‖²/(2ℓ²)
            continue
        sa = xph[2 * f]
        ca = xph[2 * f + 1]
        if kind == KIND_PERIODIC:
            c2 = 1.0 / (2.0 * params[f, 0] * params[f, 0])
            for i in range(lo, hi):
                s = sa * Ph[i, 2 * f + 1] - ca * Ph[i, 2 * f]      # sin(a − a_i) = sin(π d/ψ) (mod π)
                out[i] -= (s * s) * c2                             # −sin²(π d/ψ)/(2σ2²)
        else:
            c1 = 1.0 / (2.0 * params[f, 0] * params[f, 0])
            c2 = 1.0 / (2.0 * params[f, 1] * params[f, 1])
            x0 = x[start]
            if kind == KIND_LOCALLY_PERIODIC_ZERO_MEAN:            # its periodic part multiplies below
                for i in range(lo, hi):
                    d = x0 - X[i, start]
                    out[i] -= (d * d) * c1                         # −d²/(2σ1²)
                continue
            for i in range(lo, hi):
                d = x0 - X[i, start]
                s = sa * Ph[i, 2 * f + 1] - ca * Ph[i, 2 * f]
                out[i] -= (d * d) * c1 + (s * s) * c2              # −d²/(2σ1²) − sin²(π d/ψ)/(2σ2²)
    for i in range(lo, hi):
        out[i] = w[i] * _exp_nonpositive(out[i])
    for f in range(kinds.shape[0]):                                # zero-mean factors: (p − c0)/(1 − c0)
        if kinds[f] == KIND_LOCALLY_PERIODIC_ZERO_MEAN:
            c2 = 1.0 / (2.0 * params[f, 1] * params[f, 1])
            c0 = _i0e_nb(0.5 * c2)                                 # a = 1/(4σ2²)
            sa = xph[2 * f]
            ca = xph[2 * f + 1]
            for i in range(lo, hi):
                s = sa * Ph[i, 2 * f + 1] - ca * Ph[i, 2 * f]
                out[i] *= (math.exp(-(s * s) * c2) - c0) / (1.0 - c0)
    for i in range(lo, hi):                                        # below the floor: 0 (no subnormals)
        v = out[i]
        out[i] = v if abs(v) >= KERNEL_FLOOR else 0.0
