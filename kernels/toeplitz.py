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

Levinson–Durbin (whitening, ``log det``, solves; exact or of order m) is :mod:`kernels.levinson`.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft
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
    "DENSE_LIMIT",
]

#: Largest N solved by a dense Cholesky factorisation in :class:`ToeplitzSolver`.
DENSE_LIMIT = 1500
#: :meth:`ToeplitzSolver.solve` warns when PCG ends above ``WARN_FACTOR · tol`` (double-precision FFT
#: products put a floor near 1e-13–1e-12 on the attainable relative residual).
WARN_FACTOR = 100.0
#: Lags whose kernel value is below this fraction of the peak are dropped from the FFT embedding.
BAND_RTOL = 1e-22
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
