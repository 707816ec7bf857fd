"""Symmetric positive definite Toeplitz systems: FFT products, circulant preconditioners, PCG,
and the log-determinant (method §4).

When ``x(k)`` is the sample time on a uniform grid, a stationary kernel gives
``A = Ω + γ⁻¹I`` with ``A_ij = t_|i−j|``: a symmetric Toeplitz matrix defined by its
first column ``t``. This module works with that column only:

* :class:`SymmetricToeplitz` — ``A x`` by circulant embedding of size ``M ≥ 2N−1``
  (``O(N log N)`` time, ``O(N)`` memory).
* :func:`strang_eigenvalues`, :func:`tchan_eigenvalues` — the circulant preconditioners of
  G. Strang (copy the central diagonals) and T. Chan (the Frobenius-optimal circulant,
  ``s_j = ((N−j) t_j + j t_{N−j})/N``), diagonalised by the FFT. Strang's is not positive
  definite when the kernel has not decayed by half the record (``σ1`` long compared with
  ``N Ts``); T. Chan's is positive definite whenever ``A`` is (its eigenvalues are Rayleigh
  quotients of ``A`` at the Fourier vectors).
* :func:`pcg` — preconditioned conjugate gradients for several right-hand sides at once.
* :class:`ToeplitzSolver` — the automatic choice: dense Cholesky for small ``N``, else PCG with
  Strang, falling back to T. Chan when Strang has a non-positive eigenvalue.
* :func:`levinson_whiten`, :func:`levinson_solve` — ``L⁻¹X`` (whitening, with ``log det``) and
  ``A⁻¹X`` by Levinson–Durbin: exact in ``O(N²)``, whatever the conditioning.
* :func:`toeplitz_logdet` — ``log det A`` by Levinson–Durbin (``O(N²)`` time, ``O(N)`` memory):
  the sum of the logs of the prediction-error variances.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft
from numba import njit
from scipy.linalg import LinAlgError, cho_factor, cho_solve, toeplitz

__all__ = [
    "SymmetricToeplitz",
    "CirculantPreconditioner",
    "strang_eigenvalues",
    "tchan_eigenvalues",
    "PCGResult",
    "pcg",
    "ToeplitzSolver",
    "solve_spd_toeplitz",
    "toeplitz_logdet",
    "levinson_whiten",
    "levinson_solve",
    "DENSE_LIMIT",
]

#: Largest N solved by a dense Cholesky factorisation in :class:`ToeplitzSolver`.
DENSE_LIMIT = 1500
#: :meth:`ToeplitzSolver.solve` warns when PCG ends above ``WARN_FACTOR · tol`` (double-precision FFT
#: products put a floor near 1e-13–1e-12 on the attainable relative residual).
WARN_FACTOR = 100.0
#: Lags whose kernel value is below this fraction of the peak are dropped from the FFT embedding.
BAND_RTOL = 1e-22
#: Reflection coefficients below this are zero (a short kernel's predictor would otherwise decay into
#: subnormal numbers, whose arithmetic is ~100× slower); column entries below ``SUBNORMAL_RTOL`` of the
#: peak are zeroed for the same reason. Both are far below double-precision resolution.
KAPPA_FLUSH = 1e-150
SUBNORMAL_RTOL = 1e-280
#: Threads for scipy.fft (the machines have 2 cores).
_WORKERS = 2


def _first_column(column) -> np.ndarray:
    t = np.asarray(column, dtype=np.float64)
    if t.ndim != 1 or t.size == 0:
        raise ValueError(f"a Toeplitz first column must be a non-empty 1-D array, got shape {t.shape}")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise ValueError(f"the Toeplitz first column has a non-finite value at lag {bad[0]}")
    return t


def _levinson_column(column) -> np.ndarray:
    """:func:`_first_column` with entries below ``SUBNORMAL_RTOL`` of the peak set to zero."""
    t = _first_column(column)
    tiny = np.abs(t) < SUBNORMAL_RTOL * np.abs(t).max()
    if tiny.any() and np.any(t[tiny] != 0.0):
        t = np.where(tiny, 0.0, t)
    return t


class SymmetricToeplitz:
    """Symmetric Toeplitz operator ``A_ij = t_|i−j|`` with FFT matrix–vector products.

    The circulant embedding has first column ``[t_0 … t_w, 0 …, t_w … t_1]`` of length
    ``M = next_fast_len(N + w)``; ``A x`` is the first ``N`` entries of its product with
    ``[x; 0]``. ``w ≤ N − 1`` is the bandwidth: the last lag with ``|t_k| > BAND_RTOL·max|t|``
    (entries below ``1e-22`` of the peak change a product by less than ``1e-22·N`` relative, far
    below double precision; for the locally periodic kernel ``w ≈ 10 σ1/Ts``, which halves the
    FFT length on long records). Only ``t`` and the ``M/2 + 1`` real eigenvalues are stored.
    """

    def __init__(self, column):
        self.column = _first_column(column)
        n = self.column.size
        self.n = n
        big = np.flatnonzero(np.abs(self.column) > BAND_RTOL * np.abs(self.column).max())
        self.bandwidth = int(big[-1]) if big.size else 0
        w = self.bandwidth
        self.size = sfft.next_fast_len(max(n + w, 1), real=True)
        emb = np.zeros(self.size)
        emb[: w + 1] = self.column[: w + 1]
        if w > 0:
            emb[self.size - w:] = self.column[w:0:-1]
        self._eig = sfft.rfft(emb).real  # symmetric embedding: real spectrum

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n, self.n)

    def matvec(self, x) -> np.ndarray:
        """``A x`` for ``x`` of shape (N,) or (N, r)."""
        x = np.asarray(x, dtype=np.float64)
        if x.shape[0] != self.n:
            raise ValueError(f"operand has {x.shape[0]} rows, the Toeplitz matrix is {self.n}×{self.n}")
        if x.ndim == 1:
            return self.matvec_rows(x[None, :])[0]
        return self.matvec_rows(np.ascontiguousarray(x.T)).T

    def matvec_rows(self, xr) -> np.ndarray:
        """``A x`` for each row of ``xr`` (shape (r, N)): the layout :func:`pcg` uses (FFT along rows)."""
        X = sfft.rfft(xr, n=self.size, axis=-1, workers=_WORKERS)
        X *= self._eig
        return sfft.irfft(X, n=self.size, axis=-1, workers=_WORKERS)[:, : self.n]

    __matmul__ = matvec

    def to_dense(self) -> np.ndarray:
        """The full matrix (tests and small N only)."""
        return toeplitz(self.column)


def strang_eigenvalues(column) -> np.ndarray:
    """Eigenvalues (``rfft`` order, ``N//2 + 1`` values) of G. Strang's circulant preconditioner.

    First column ``s_j = t_j`` for ``j ≤ N/2`` and ``s_j = t_{N−j}`` above.
    """
    t = _first_column(column)
    n = t.size
    s = t.copy()
    j = np.arange(n)
    upper = j > n // 2
    s[upper] = t[n - j[upper]]
    return sfft.rfft(s).real


def tchan_eigenvalues(column) -> np.ndarray:
    """Eigenvalues (``rfft`` order) of T. Chan's optimal circulant preconditioner.

    First column ``s_j = ((N − j) t_j + j t_{N−j}) / N``; positive when ``A`` is SPD.
    """
    t = _first_column(column)
    n = t.size
    j = np.arange(n)
    wrap = np.zeros(n)
    wrap[1:] = t[:0:-1]  # t_{N−j}
    s = ((n - j) * t + j * wrap) / n
    return sfft.rfft(s).real


class CirculantPreconditioner:
    """``M⁻¹ r`` for a circulant ``M`` given its eigenvalues (``rfft`` order)."""

    def __init__(self, eigenvalues, n: int, kind: str):
        self.eigenvalues = np.asarray(eigenvalues, dtype=np.float64)
        self.n = n
        self.kind = kind
        if not np.all(self.eigenvalues > 0):
            raise ValueError(f"the {kind} circulant preconditioner is not positive definite "
                             f"(smallest eigenvalue {self.eigenvalues.min():.3g})")

    def solve(self, r) -> np.ndarray:
        """``M⁻¹ r`` for ``r`` of shape (N,) or (N, k)."""
        r = np.asarray(r, dtype=np.float64)
        if r.ndim == 1:
            return self.solve_rows(r[None, :])[0]
        return self.solve_rows(np.ascontiguousarray(r.T)).T

    def solve_rows(self, rr) -> np.ndarray:
        """``M⁻¹ r`` for each row of ``rr`` (shape (k, N))."""
        R = sfft.rfft(rr, axis=-1, workers=_WORKERS)
        R /= self.eigenvalues
        return sfft.irfft(R, n=self.n, axis=-1, workers=_WORKERS)

    __call__ = solve


@dataclass(frozen=True)
class PCGResult:
    """Solution of :func:`pcg` and its convergence record."""

    x: np.ndarray
    iterations: int  # largest iteration count over the right-hand sides
    residual: float  # largest final relative residual ‖b − A x‖ / ‖b‖ (recomputed, not recurrence)
    converged: bool


def pcg(matvec_rows, B, *, preconditioner=None, tol: float = 1e-12, max_iter: int = 1000,
        max_restarts: int = 3) -> PCGResult:
    """Preconditioned conjugate gradients for SPD ``A X = B`` with one or several right-hand sides.

    Each right-hand side runs its own CG recurrence; they are advanced together so that every
    iteration costs one batched product and one batched preconditioner solve. A column stops when
    its recurrence residual reaches ``tol · ‖b‖``; the true residual is then recomputed and, if
    the recurrence has drifted above ``tol``, CG restarts from the current iterate (at most
    ``max_restarts`` times). ``residual`` reports the attained (true) accuracy.

    Parameters
    ----------
    matvec_rows : callable
        ``V ↦ A V`` applied to each **row** of ``V`` (shape (r, N)); e.g.
        :meth:`SymmetricToeplitz.matvec_rows`. Rows keep the FFTs contiguous.
    B : array (N,) or (N, r)
        Right-hand sides as columns (the usual ``solve`` convention); ``x`` has the same shape.
    preconditioner : callable, optional
        ``V ↦ M⁻¹ V`` row-wise for SPD ``M`` (e.g. :meth:`CirculantPreconditioner.solve_rows`).
    tol : float
        Relative residual target per right-hand side.
    max_iter : int
        Iterations per right-hand side (over all restarts).
    """
    B = np.asarray(B, dtype=np.float64)
    single = B.ndim == 1
    Br = np.ascontiguousarray(B[None, :] if single else B.T)  # (r, N)
    r = Br.shape[0]
    precond = preconditioner if preconditioner is not None else (lambda v: v.copy())
    X = np.zeros_like(Br)
    bnorm = np.sqrt(np.sum(Br * Br, axis=1))
    bnorm_safe = np.where(bnorm > 0, bnorm, 1.0)
    iters = np.zeros(r, dtype=np.int64)
    R = Br.copy()
    for _restart in range(max_restarts + 1):
        active = np.flatnonzero(np.sqrt(np.sum(R * R, axis=1)) > tol * bnorm_safe)
        active = active[iters[active] < max_iter]
        if active.size == 0:
            break
        Ra = R[active]
        Xa = X[active]
        Za = precond(Ra)
        P = Za.copy()
        rz = np.sum(Ra * Za, axis=1)
        thr = tol * bnorm_safe[active]
        while active.size:
            AP = matvec_rows(P)
            pap = np.sum(P * AP, axis=1)
            ok = pap > 0
            alpha = np.where(ok, rz / np.where(ok, pap, 1.0), 0.0)[:, None]
            Xa += alpha * P
            Ra -= alpha * AP
            iters[active] += 1
            rnorm = np.sqrt(np.sum(Ra * Ra, axis=1))
            done = (rnorm <= thr) | (iters[active] >= max_iter) | ~ok
            if done.any():
                X[active[done]] = Xa[done]
                keep = ~done
                active, Ra, Xa, P, rz, thr = active[keep], Ra[keep], Xa[keep], P[keep], rz[keep], thr[keep]
                if active.size == 0:
                    break
            Za = precond(Ra)
            rz_new = np.sum(Ra * Za, axis=1)
            P = Za + (rz_new / rz)[:, None] * P
            rz = rz_new
        R = Br - matvec_rows(X)
    res = np.sqrt(np.sum(R * R, axis=1)) / bnorm_safe
    res[bnorm == 0] = 0.0
    worst = float(res.max()) if r else 0.0
    return PCGResult(x=X[0] if single else X.T, iterations=int(iters.max()) if r else 0,
                     residual=worst, converged=worst <= tol)


class ToeplitzSolver:
    """Solves ``A X = B`` for SPD symmetric Toeplitz ``A`` (first column ``t``), choosing the method.

    * ``N ≤ dense_limit``: dense Cholesky of the full matrix (``method = 'dense'``).
    * otherwise PCG with FFT products and G. Strang's circulant preconditioner
      (``'pcg-strang'``); when Strang's circulant has a non-positive eigenvalue (kernel still
      correlated at half the record, e.g. ``σ1`` long compared with ``N Ts``) T. Chan's
      preconditioner, which is SPD for SPD ``A``, is used instead (``'pcg-tchan'``).

    ``preconditioner`` may force ``'strang'`` (raises if not SPD) or ``'tchan'``.
    After :meth:`solve`, ``iterations`` and ``residual`` describe the last PCG run.
    """

    def __init__(self, column, *, tol: float = 1e-12, max_iter: int | None = None,
                 dense_limit: int = DENSE_LIMIT, preconditioner: str = "auto"):
        self.column = _first_column(column)
        self.n = self.column.size
        self.tol = float(tol)
        self.max_iter = int(max_iter) if max_iter is not None else max(200, min(self.n, 5000))
        self.iterations = 0
        self.residual = 0.0
        if preconditioner not in ("auto", "strang", "tchan"):
            raise ValueError(f"preconditioner must be 'auto', 'strang' or 'tchan', got {preconditioner!r}")
        self._chol = None
        if self.n <= dense_limit:
            try:
                self._chol = cho_factor(toeplitz(self.column), lower=True, check_finite=False)
            except LinAlgError:
                raise ValueError("the Toeplitz matrix is not positive definite (Cholesky failed); "
                                 "check the kernel parameters and use γ < ∞") from None
            self.method = "dense"
            return
        self.operator = SymmetricToeplitz(self.column)
        eig = None
        kind = "strang"
        if preconditioner in ("auto", "strang"):
            eig = strang_eigenvalues(self.column)
            if not np.all(eig > 1e-12 * np.abs(eig).max()):
                if preconditioner == "strang":
                    raise ValueError("the Strang preconditioner is not positive definite for this matrix "
                                     f"(smallest eigenvalue {eig.min():.3g}); use 'tchan' or 'auto'")
                eig = None
        if eig is None:
            eig = tchan_eigenvalues(self.column)
            kind = "tchan"
            if not np.all(eig > 0):
                raise ValueError("the Toeplitz matrix is not positive definite (T. Chan circulant has a "
                                 f"non-positive eigenvalue {eig.min():.3g}); check the kernel parameters")
        self.preconditioner = CirculantPreconditioner(eig, self.n, kind)
        self.method = f"pcg-{kind}"

    def logdet_dense(self) -> float:
        """``log det A`` from the Cholesky factor (dense method only)."""
        if self._chol is None:
            raise ValueError("logdet_dense needs the dense method; use toeplitz_logdet(column)")
        return 2.0 * float(np.sum(np.log(np.diag(self._chol[0]))))

    def solve(self, B, tol: float | None = None) -> np.ndarray:
        """``A⁻¹ B`` for ``B`` of shape (N,) or (N, r) (``tol`` overrides the PCG tolerance once).

        Emits a ``RuntimeWarning`` when PCG stops above ``WARN_FACTOR · tol`` (attained: ``residual``).
        """
        B = np.asarray(B, dtype=np.float64)
        if B.shape[0] != self.n:
            raise ValueError(f"right-hand side has {B.shape[0]} rows, the system has {self.n}")
        if self._chol is not None:
            self.iterations = 0
            return cho_solve(self._chol, B, check_finite=False)
        tol = self.tol if tol is None else float(tol)
        res = pcg(self.operator.matvec_rows, B, preconditioner=self.preconditioner.solve_rows, tol=tol,
                  max_iter=self.max_iter)
        self.iterations = res.iterations
        self.residual = res.residual
        if res.residual > WARN_FACTOR * tol:
            warnings.warn(f"Toeplitz PCG ({self.method}) reached relative residual {res.residual:.2g} after "
                          f"{res.iterations} iterations, above tol={tol:.2g}", RuntimeWarning, stacklevel=2)
        return res.x


def solve_spd_toeplitz(column, B, **kwargs) -> np.ndarray:
    """``A⁻¹ B`` for the SPD symmetric Toeplitz matrix with first column ``column``
    (:class:`ToeplitzSolver` options as keywords)."""
    return ToeplitzSolver(column, **kwargs).solve(B)


#: Numba options of the Levinson kernels: re-association lets the lagged dot products vectorise
#: (without it they run ~2× slower); NaN/inf semantics are kept (no "nnan"/"ninf"). BLAS is not used
#: on purpose: a BLAS dot per step oversubscribes threads on a loaded machine (20× slower measured).
_FAST = {"reassoc", "contract"}


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
    reversed (``trev[i] = t[N−1−i]``, so that the lagged products are contiguous): updates the
    predictor ``a`` in place (reflection coefficient ``κ = a[k]``) and returns the new
    prediction-error variance ``E_k = E_{k−1}(1 − κ²)``. ``buf`` is scratch of length N."""
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
def _levinson_logdet(t):
    """Levinson–Durbin on the normalised column; returns (log det, failing order or −1)."""
    n = t.shape[0]
    r0 = t[0]
    if not r0 > 0.0:
        return 0.0, 0
    trev = (t / r0)[::-1].copy()
    a = np.zeros(n)
    buf = np.zeros(n)
    e = 1.0  # prediction-error variance / r0
    logdet = n * math.log(r0)
    for k in range(1, n):
        e = _durbin_step(trev, a, buf, e, k)
        if not e > 0.0:
            return 0.0, k
        logdet += math.log(e)
    return logdet, -1


@njit(cache=True, nogil=True)
def _levinson_whiten(t, Xr, lengths, W, logdets):
    """Durbin recursion up to order ``max(lengths) − 1``; row ``k`` of every series is replaced by its
    normalised innovation ``(x_k − Σ_j a_j^(k) x_{k−j}) / √E_k``. ``Xr`` (S, r, L) holds the
    zero-padded series **reversed** along the last axis (``Xr[..., L−1−k] = x_k``, contiguous
    lagged products); ``W`` (S, r, L) receives the innovations in natural order."""
    n = t.shape[0]
    S = Xr.shape[0]
    r = Xr.shape[1]
    L = Xr.shape[2]
    r0 = t[0]
    if not r0 > 0.0:
        return 0
    trev = (t / r0)[::-1].copy()
    a = np.zeros(n)
    buf = np.zeros(n)
    e = 1.0
    inv = 1.0 / math.sqrt(r0)
    for s in range(S):
        logdets[s] = math.log(r0)
        for c in range(r):
            W[s, c, 0] = Xr[s, c, L - 1] * inv
    for k in range(1, n):
        e = _durbin_step(trev, a, buf, e, k)
        if not e > 0.0:
            return k
        inv = 1.0 / math.sqrt(e * r0)
        le = math.log(e * r0)
        for s in range(S):
            if k < lengths[s]:
                logdets[s] += le
                c = 0
                while c + 1 < r:
                    x0 = Xr[s, c]
                    x1 = Xr[s, c + 1]
                    s0, s1 = _dot_rev2(a, x0, x1, L - k, k)
                    W[s, c, k] = (x0[L - 1 - k] - s0) * inv
                    W[s, c + 1, k] = (x1[L - 1 - k] - s1) * inv
                    c += 2
                if c < r:
                    x = Xr[s, c]
                    W[s, c, k] = (x[L - 1 - k] - _dot_rev(a, x, L - k, k)) * inv
    return -1


@njit(cache=True, nogil=True, fastmath=_FAST)
def _levinson_solve(t, Xr, outr):
    """``A⁻¹ X`` row-wise in one Durbin pass: ``A⁻¹ = L⁻ᵀ L⁻¹`` where row k of ``L⁻¹`` is
    ``[−a_k … −a_1, 1]/√E_k``; the innovation ``w_k = (L⁻¹x)_k`` is known at step k, and its
    contribution ``w_k · row_k(L⁻¹)`` to ``L⁻ᵀw`` is added at once. ``Xr`` (r, N) and the
    result ``outr`` (r, N, zeroed by the caller) are stored reversed along the last axis."""
    n = t.shape[0]
    r = Xr.shape[0]
    r0 = t[0]
    if not r0 > 0.0:
        return 0
    trev = (t / r0)[::-1].copy()
    a = np.zeros(n)
    buf = np.zeros(n)
    e = 1.0
    for c in range(r):
        outr[c, n - 1] += Xr[c, n - 1] / r0
    for k in range(1, n):
        e = _durbin_step(trev, a, buf, e, k)
        if not e > 0.0:
            return k
        inv2 = 1.0 / (e * r0)
        lo = n - k
        for c in range(r):
            x = Xr[c]
            w = (x[n - 1 - k] - _dot_rev(a, x, lo, k)) * inv2
            o = outr[c]
            o[n - 1 - k] += w
            for j in range(1, k + 1):
                o[lo + j - 1] -= a[j] * w
    return -1


def levinson_solve(column, B) -> np.ndarray:
    """``A⁻¹ B`` for the SPD symmetric Toeplitz ``A`` (first column ``column``) by Levinson–Durbin.

    Exact direct solve in ``O(N² (1 + 2r))`` time and ``O(N r)`` memory for ``r`` right-hand
    sides, independent of the conditioning that slows PCG (long correlation σ1, large γ);
    Levinson–Durbin is weakly stable (error ∝ condition number · ε). ``B`` (N,) or (N, r).
    """
    t = _levinson_column(column)
    B = np.asarray(B, dtype=np.float64)
    single = B.ndim == 1
    if B.shape[0] != t.size:
        raise ValueError(f"right-hand side has {B.shape[0]} rows, the system has {t.size}")
    Xr = np.ascontiguousarray((B[:, None] if single else B).T[:, ::-1])
    outr = np.zeros_like(Xr)
    fail = _levinson_solve(t, Xr, outr)
    out = outr[:, ::-1]
    if fail >= 0:
        raise ValueError(f"the Toeplitz matrix is not positive definite (leading minor of order {fail + 1} "
                         "is not positive); check the kernel parameters")
    return out[0] if single else out.T


def levinson_whiten(column, series, lengths=None):
    """Whiten series with the inverse Cholesky factor of the SPD Toeplitz matrix (Levinson–Durbin).

    ``series`` (S, r, L): S segments of r series each, zero-padded to ``L = len(column)``;
    ``lengths`` (S,) their true lengths (default all L). Returns ``(W, logdets)`` with
    ``W[s, :, :n_s] = L_{n_s}⁻¹ x`` row-wise (``A_{n_s} = L Lᵀ``, the leading block of A) and
    ``logdets[s] = log det A_{n_s}``. ``O(L² (1 + S r))`` time (contiguous dot products), ``O(S r L)`` memory.
    """
    t = _levinson_column(column)
    X = np.ascontiguousarray(series, dtype=np.float64)
    if X.ndim != 3 or X.shape[2] != t.size:
        raise ValueError(f"series must have shape (S, r, {t.size}), got {X.shape}")
    lengths = np.full(X.shape[0], t.size, dtype=np.int64) if lengths is None else np.asarray(lengths, dtype=np.int64)
    W = np.zeros_like(X)
    logdets = np.zeros(X.shape[0])
    Xr = np.ascontiguousarray(X[:, :, ::-1])
    fail = _levinson_whiten(t, Xr, lengths, W, logdets)
    if fail >= 0:
        raise ValueError(f"the Toeplitz matrix is not positive definite (leading minor of order {fail + 1} "
                         "is not positive); check the kernel parameters")
    return W, logdets


def toeplitz_logdet(column) -> float:
    """``log det A`` of an SPD symmetric Toeplitz matrix (first column ``column``).

    Levinson–Durbin recursion: ``det A = Π_k E_k`` with ``E_k`` the order-``k`` one-step
    prediction-error variance of the stationary sequence with autocovariance ``t``.
    ``O(N²)`` time, ``O(N)`` memory. Raises ``ValueError`` if ``A`` is not positive definite.
    """
    t = _levinson_column(column)
    logdet, fail = _levinson_logdet(t)
    if fail >= 0:
        raise ValueError(f"the Toeplitz matrix is not positive definite (leading minor of order {fail + 1} "
                         "is not positive); check the kernel parameters")
    return float(logdet)
