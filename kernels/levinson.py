"""Levinson–Durbin for SPD symmetric Toeplitz ``A`` (first column ``t``): the inverse Cholesky factor,
exact or truncated at order m, for whitening, ``log|A|`` and solves (method §4).

The exact inverse Cholesky factor of ``A`` has row ``k``

    (L⁻¹)_k = [−a_k^(k) … −a_1^(k), 1] / √E_k                                                 (V1)

(the order-k one-step predictor of the stationary sequence with autocovariance ``t`` and its error
variance ``E_k``), so ``log|A| = Σ_k log E_k`` and ``L⁻¹x`` are the innovations of ``x`` — ``O(N²)``
time, ``O(N)`` memory, whatever the conditioning (Levinson–Durbin is weakly stable: error ∝ condition
number · ε; long σ1 with large γ stall PCG, not Levinson).

**Order m** (a Vecchia approximation on the past m samples): beyond the lag where the predictor has
converged ``a^(k) ≈ a^(m)`` and ``E_k ≈ E_m``. Rows ``k ≤ m`` are kept exact, every later row uses the
order-m predictor:

    w_k = (x_k − Σ_{j=1..m} a_j^(m) x_{k−j}) / √E_m,   log|Ã| = Σ_{k≤m} log E_k + (N − 1 − m) log E_m   (V2)

— the exact likelihood of the Gaussian process whose law given its past is the order-m
autoregression: ``Ã = L̃L̃ᵀ`` is a valid covariance, so REML, GLS and their covariance keep their
meaning. The later rows are one FIR filter, applied by FFT (overlap-add): ``O(m² r + N r log m)`` for
r series. The error in ``log|A|`` is

    log|Ã| − log|A| = Σ_{j > m} (N − j) · (−log(1 − κ_j²)) ≥ 0                                  (V3)

with ``κ_j`` the reflection coefficients beyond m. :func:`levinson_whiten` stops at the first
checkpoint (every :data:`CHECK_EVERY` lags from ``max(MIN_ORDER, min_order)``) where the
contribution (V3) of the lags ``(k/2, k]`` already passed is below ``tol`` — short-memory kernels'
reflection coefficients decay geometrically beyond it — or at ``max_order``, and reports that
contribution (:attr:`Whitening.tail_estimate`). ``min_order`` keeps a kernel that is ~0 between the
multiples of a long period (no small reflection coefficient shows that a longer memory would not
matter) from stopping before its support. With ``m ≥ N − 1`` everything is exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.signal import oaconvolve

from .toeplitz import _first_column

__all__ = ["Whitening", "levinson_whiten", "levinson_solve", "toeplitz_logdet", "MIN_ORDER", "CHECK_EVERY",
           "KAPPA_FLUSH", "SUBNORMAL_RTOL"]

#: the lowest order at which the stop criterion (V3) is tested
MIN_ORDER = 256
#: the criterion is tested every CHECK_EVERY lags
CHECK_EVERY = 128
#: Reflection coefficients below this are zero (a short kernel's predictor would otherwise decay into
#: subnormal numbers, whose arithmetic is ~100× slower); column entries below ``SUBNORMAL_RTOL`` of the
#: peak are zeroed for the same reason. Both are far below double-precision resolution.
KAPPA_FLUSH = 1e-150
SUBNORMAL_RTOL = 1e-280
#: Numba options of the Levinson kernels: re-association lets the lagged dot products vectorise
#: (without it they run ~2× slower); NaN/inf semantics are kept (no "nnan"/"ninf"). BLAS is not used
#: on purpose: a BLAS dot per step oversubscribes threads on a loaded machine (20× slower measured).
_FAST = {"reassoc", "contract"}


def _levinson_column(column) -> np.ndarray:
    """:func:`kernels.toeplitz._first_column` with entries below ``SUBNORMAL_RTOL`` of the peak set to zero."""
    t = _first_column(column)
    tiny = np.abs(t) < SUBNORMAL_RTOL * np.abs(t).max()
    if tiny.any() and np.any(t[tiny] != 0.0):
        t = np.where(tiny, 0.0, t)
    return t


@njit(cache=True, nogil=True, fastmath=_FAST)
def _dot_rev(a, x, lo, k):
    """``Σ_{j=1..k} a[j] x[lo + j − 1]`` (contiguous lagged product, ``x`` stored reversed)."""
    acc = 0.0
    for j in range(1, k + 1):
        acc += a[j] * x[lo + j - 1]
    return acc


@njit(cache=True, nogil=True, fastmath=_FAST)
def _dot_rev2(a, x0, x1, lo, k):
    """:func:`_dot_rev` of two series in one pass over ``a`` (~25 % faster than two passes)."""
    s0 = 0.0
    s1 = 0.0
    for j in range(1, k + 1):
        aj = a[j]
        s0 += aj * x0[lo + j - 1]
        s1 += aj * x1[lo + j - 1]
    return s0, s1


@njit(cache=True, nogil=True, fastmath=_FAST)
def _durbin_step(trev, a, buf, e, k):
    """Order ``k`` of the Durbin recursion (Golub & Van Loan §4.7) on the normalised column, given
    reversed (``trev[i] = t[L−1−i]``, so that the lagged products are contiguous): updates the
    predictor ``a`` in place (reflection coefficient ``κ = a[k]``) and returns the new
    prediction-error variance ``E_k = E_{k−1}(1 − κ²)``. ``buf`` is scratch of length L."""
    n = trev.shape[0]
    kappa = (trev[n - 1 - k] - _dot_rev(a, trev, n - k, k - 1)) / e
    if abs(kappa) < KAPPA_FLUSH:  # nothing left to predict at this lag: keep the predictor exact
        a[k] = 0.0                # (and free of subnormal numbers, which are ~100× slower)
        return e
    for j in range(1, k):
        buf[j] = a[k - j]
    for j in range(1, k):
        a[j] -= kappa * buf[j]
    a[k] = kappa
    return e * (1.0 - kappa) * (1.0 + kappa)


@njit(cache=True, nogil=True)
def _whiten_head(trev, Xr, n_total, m_min, tol, W, a, ell):
    """Durbin to order ≤ ``L − 1`` with the innovations (V1) of the first L rows; stops at the first
    checkpoint from ``m_min`` on where ``Σ_{j ∈ (k/2, k]} (n_total − j) ℓ_j < tol`` (V3). ``trev``: the
    column / t_0, reversed, length L; ``Xr`` (r, L) the first L rows, reversed; ``W`` (r, L) receives
    the innovations times √t_0. Returns ``(m, Σ_{k≤m} log E_k (normalised), E_m, tail, failing order)``."""
    L = trev.shape[0]
    r = Xr.shape[0]
    buf = np.zeros(L)
    e = 1.0
    for c in range(r):
        W[c, 0] = Xr[c, L - 1]
    logdet = 0.0
    for k in range(1, L):
        e = _durbin_step(trev, a, buf, e, k)
        if not e > 0.0:
            return k, 0.0, 0.0, 0.0, k
        kap = a[k]
        ell[k] = -math.log1p(-kap * kap)
        logdet += math.log(e)
        inv = 1.0 / math.sqrt(e)
        c = 0
        while c + 1 < r:
            x0 = Xr[c]
            x1 = Xr[c + 1]
            s0, s1 = _dot_rev2(a, x0, x1, L - k, k)
            W[c, k] = (x0[L - 1 - k] - s0) * inv
            W[c + 1, k] = (x1[L - 1 - k] - s1) * inv
            c += 2
        if c < r:
            x = Xr[c]
            W[c, k] = (x[L - 1 - k] - _dot_rev(a, x, L - k, k)) * inv
        if k >= m_min and k % CHECK_EVERY == 0 and k < L - 1:
            tail = 0.0
            for j in range(k // 2 + 1, k + 1):
                tail += (n_total - j) * ell[j]
            if tail < tol:
                return k, logdet, e, tail, -1
    m = L - 1
    tail = 0.0
    for j in range(m // 2 + 1, m + 1):
        tail += (n_total - j) * ell[j]
    return m, logdet, e, tail, -1


@njit(cache=True, nogil=True, fastmath=_FAST)
def _solve_head(trev, Xr, m, outr):
    """Rows ``k ≤ m`` of ``L⁻ᵀL⁻¹x`` (V1) in one Durbin pass: the innovation of row k over ``E_k`` is
    known at step k and added at once along row k of ``L⁻¹``. ``Xr``, ``outr`` (r, N, ``outr`` zeroed by
    the caller) stored reversed along the last axis; the result is over ``t_0``."""
    L = trev.shape[0]
    n = Xr.shape[1]
    r = Xr.shape[0]
    a = np.zeros(L)
    buf = np.zeros(L)
    e = 1.0
    for c in range(r):
        outr[c, n - 1] += Xr[c, n - 1]
    for k in range(1, m + 1):
        e = _durbin_step(trev, a, buf, e, k)
        if not e > 0.0:
            return k
        inv = 1.0 / e
        lo = n - k
        for c in range(r):
            x = Xr[c]
            w = (x[n - 1 - k] - _dot_rev(a, x, lo, k)) * inv
            o = outr[c]
            o[n - 1 - k] += w
            for j in range(1, k + 1):
                o[lo + j - 1] -= a[j] * w
    return -1


def _not_pd(order: int) -> ValueError:
    return ValueError(f"the Toeplitz matrix is not positive definite (leading minor of order {order + 1} is not "
                      "positive); check the kernel parameters")


def _prepare(column, n: int, max_order: int | None) -> tuple[np.ndarray, float, int]:
    """``(trev, t_0, m_max)``: the normalised column reversed up to the highest order allowed."""
    if max_order is not None and int(max_order) < 1:
        raise ValueError(f"the order must be a positive number of lags, got {max_order!r}")
    m_max = n - 1 if max_order is None else min(int(max_order), n - 1)
    column = np.asarray(column, dtype=np.float64)
    if column.ndim != 1 or column.size < m_max + 1:
        raise ValueError(f"the Toeplitz first column must be 1-D with at least {m_max + 1} lags, got shape {column.shape}")
    t = _levinson_column(column[: m_max + 1])
    r0 = float(t[0])
    if not r0 > 0.0:
        raise _not_pd(0)
    return (t / r0)[::-1].copy(), r0, m_max


@dataclass(frozen=True)
class Whitening:
    """Result of :func:`levinson_whiten`: ``white`` (N, r) the innovations (V2), ``logdet`` = log|Ã|,
    ``order`` = m (``N − 1``: exact), ``tail_estimate`` the contribution (V3) of the lags (m/2, m] —
    what the lags beyond m would add when they decay no slower —, ``predictor`` ``[1, −a_1 … −a_m]`` and
    ``variance`` ``E_m`` of the order-m predictor."""

    white: np.ndarray
    logdet: float
    order: int
    tail_estimate: float
    predictor: np.ndarray
    variance: float

    @property
    def exact(self) -> bool:
        return self.order >= self.white.shape[0] - 1


def levinson_whiten(column, X, *, max_order: int | None = None, tol: float = 0.0, min_order: int = 0) -> Whitening:
    """Innovations ``L̃⁻¹X`` (V1, V2) of the columns of ``X`` (N, r) and ``log|Ã|``.

    ``column``: the first column of ``A`` (at least ``min(N, max_order + 1)`` lags; later ones are not
    read). Exact by default; ``max_order`` bounds the order m, ``tol > 0`` lets the criterion (V3) stop
    earlier (not before ``min_order`` nor :data:`MIN_ORDER`). ``O(m² r + N r log m)`` time, ``O(N r)``
    memory. Raises ``ValueError`` when ``A`` is not positive definite."""
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[0] < 1:
        raise ValueError(f"X must have shape (N, r) with N ≥ 1, got {X.shape}")
    n, r = X.shape
    trev, r0, m_max = _prepare(column, n, max_order)
    L = m_max + 1
    W = np.zeros((r, L))
    a = np.zeros(L)
    ell = np.zeros(L)
    m, logdet, e_m, tail, fail = _whiten_head(trev, np.ascontiguousarray(X[:L].T[:, ::-1]), n,
                                              max(MIN_ORDER, int(min_order)), float(tol), W, a, ell)
    if fail >= 0:
        raise _not_pd(fail)
    white = np.empty((n, r))
    white[: m + 1] = W[:, : m + 1].T / math.sqrt(r0)
    predictor = np.concatenate([[1.0], -a[1: m + 1]])
    logdet += n * math.log(r0)
    if m < n - 1:
        if r:
            conv = oaconvolve(X.T, predictor[None, :], axes=1)  # (r, N + m): Σ_j p_j x_{k−j} at k
            white[m + 1:] = conv[:, m + 1: n].T / math.sqrt(e_m * r0)
        logdet += (n - 1 - m) * math.log(e_m)
    return Whitening(white=white, logdet=float(logdet), order=int(m), tail_estimate=float(tail),
                     predictor=predictor, variance=float(e_m * r0))


def levinson_solve(column, B, order: int | None = None) -> np.ndarray:
    """``Ã⁻¹B = L̃⁻ᵀL̃⁻¹B`` (V1, V2): exact ``A⁻¹B`` by default, else of the order-``order``
    approximation (the rows beyond m by FFT). ``B`` (N,) or (N, r)."""
    B = np.asarray(B, dtype=np.float64)
    single = B.ndim == 1
    X = B[:, None] if single else B
    n = X.shape[0]
    if X.ndim != 2 or n < 1:
        raise ValueError(f"the right-hand side must have shape (N,) or (N, r), got {B.shape}")
    trev, r0, m = _prepare(column, n, order)
    outr = np.zeros((X.shape[1], n))
    fail = _solve_head(trev, np.ascontiguousarray(X.T[:, ::-1]), m, outr)
    if fail >= 0:
        raise _not_pd(fail)
    out = outr[:, ::-1] / r0
    if m < n - 1:
        w = levinson_whiten(column, X, max_order=m)
        u = np.zeros((X.shape[1], n))
        u[:, m + 1:] = w.white[m + 1:].T / math.sqrt(w.variance)
        # Σ_{k>m} u_k [−a_m … −a_1, 1] placed at k−m … k: the correlation of u with the predictor
        out += oaconvolve(u, w.predictor[::-1][None, :], axes=1)[:, m: m + n]
    out = out.T
    return out[:, 0] if single else out


def toeplitz_logdet(column) -> float:
    """``log det A`` of an SPD symmetric Toeplitz matrix (first column ``column``): ``Π_k E_k`` (V1),
    ``O(N²)`` time, ``O(N)`` memory. Raises ``ValueError`` if ``A`` is not positive definite."""
    t = _first_column(column)
    return levinson_whiten(t, np.zeros((t.size, 0))).logdet
