"""Ordinary least squares of the PL-ARX model (method §3, thesis eq. 2.8), and the input
validation shared with PL-LSSVM (method §4).

``β_LS = argmin ‖y − Zβ‖²`` is solved from a QR factorisation of the column-scaled
``Z``; ``(ZᵀZ)⁻¹`` is never formed. The classical covariance ``σ̂² (ZᵀZ)⁻¹`` is
computed as ``σ̂² R⁻¹R⁻ᵀ`` from the triangular factor. LS is unbiased only when the
disturbance ``f`` is white; periodic cutting forces that act through the closed loop
correlate with ``v_m`` and bias it (thesis §2.2.1) — use :func:`kernels.pl_lssvm.pl_lssvm`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular

from .errors import ParameterError

__all__ = ["LSResult", "least_squares", "validate_regression", "MIN_EXTRA_SAMPLES", "RANK_RTOL"]

#: Samples required beyond the number of estimated coefficients (residual degrees of freedom).
MIN_EXTRA_SAMPLES = 10
#: Relative singular-value threshold (on unit-norm columns) below which Z is rank deficient.
RANK_RTOL = 1e-10

_COULOMB_HINT = {
    "-sigma_p": "no motion above +Ω (no positive speed beyond the dead band)",
    "-sigma_n": "no motion below −Ω (no negative speed beyond the dead band)",
    "-tau": "the sign of the speed does not change",
    "-abs_tau": "the speed is never inside the dead band, or always",
}


def _names_for(m: int, names) -> tuple[str, ...]:
    if names is None:
        return tuple(f"z{j + 1}" for j in range(m))
    names = tuple(str(n) for n in names)
    if len(names) != m:
        raise ValueError(f"names has {len(names)} entries but Z has {m} columns")
    return names


def validate_regression(Z, y, names=None, *, intercept: bool = False):
    """Check ``Z`` (N, m) and ``y`` (N,) for a linear(-in-β) fit; return float arrays and names.

    Shared by :func:`least_squares` (``intercept=False``) and PL-LSSVM (``intercept=True``:
    the bias ``c`` of eq. 2.9 adds a column of ones, ``Z̃ = [1, Z]``).

    Raises ``ValueError`` naming the problem: shapes, the first non-finite sample of the
    named array/column, too few samples (at least ``p + MIN_EXTRA_SAMPLES`` for ``p``
    coefficients), all-zero columns (Coulomb columns without speed reversal) and
    linearly dependent columns (SVD of the unit-norm-scaled ``Z̃``, threshold ``RANK_RTOL``).
    """
    Z = np.asarray(Z, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if Z.ndim == 1:
        Z = Z[:, None]
    if Z.ndim != 2:
        raise ValueError(f"Z must be a 2-D array (samples × regressors), got shape {Z.shape}")
    if y.ndim != 1:
        raise ValueError(f"y must be a 1-D array of samples, got shape {y.shape}")
    n, m = Z.shape
    if y.shape[0] != n:
        raise ValueError(f"Z has {n} rows but y has {y.shape[0]} samples; they must align (y(k) = v_m(k+1))")
    if m == 0:
        raise ValueError("Z has no columns")
    names = _names_for(m, names)
    bad = np.flatnonzero(~np.isfinite(y))
    if bad.size:
        raise ValueError(f"y has {bad.size} non-finite value(s), first at sample {bad[0]}; "
                         "remove or interpolate them before identification")
    bad_rows, bad_cols = np.nonzero(~np.isfinite(Z))
    if bad_rows.size:
        first = int(np.argmin(bad_rows))
        j = int(bad_cols[first])
        count = int(np.sum(bad_cols == j))
        raise ValueError(f"Z column {j} ({names[j]!r}) has {count} non-finite value(s), first at sample "
                         f"{bad_rows[first]}; remove or interpolate them before identification")
    p = m + (1 if intercept else 0)
    need = p + MIN_EXTRA_SAMPLES
    if n < need:
        what = f"{m} regressors" + (" + the bias c" if intercept else "")
        raise ValueError(f"too few samples: {n}, but {p} coefficients ({what}) need at least {need} "
                         f"(coefficients + {MIN_EXTRA_SAMPLES} residual degrees of freedom); record a longer trial")
    norms = np.sqrt(np.sum(Z * Z, axis=0))
    zero = [j for j in range(m) if norms[j] == 0.0]
    if zero:
        cols = ", ".join(repr(names[j]) for j in zero)
        hints = [_COULOMB_HINT[names[j]] for j in zero if names[j] in _COULOMB_HINT]
        if hints:
            raise ParameterError(
                f"regressor column(s) {cols} are all zero: {'; '.join(hints)}. No speed reversal: "
                "drop the Coulomb columns (coulomb=False) or record a trial with reversals", "coulomb")
        raise ValueError(f"regressor column(s) {cols} are all zero; the coefficients cannot be identified")
    cols = [Z / norms]
    all_names = list(names)
    if intercept:
        cols.insert(0, np.full((n, 1), 1.0 / math.sqrt(n)))
        all_names.insert(0, "bias c (intercept)")
    S = np.hstack(cols) if len(cols) > 1 else cols[0]
    _, s, vt = np.linalg.svd(S, full_matrices=False)
    small = np.flatnonzero(s <= RANK_RTOL * s[0])
    if small.size:
        null = vt[small]  # rows span the (numerical) null space
        weight = np.sqrt(np.sum(null * null, axis=0))
        involved = [all_names[j] for j in np.flatnonzero(weight > 1e-6)]
        msg = (f"the regressors are linearly dependent (rank {p - small.size} of {p}): columns "
               f"{', '.join(repr(x) for x in involved)} are collinear, so their coefficients are not identifiable")
        if {"-sigma_p", "-sigma_n"} <= set(involved):
            msg += ("; every sample is outside the dead band ±Ω, so −σ_p − σ_n is constant: set a dead band "
                    "omega > 0 that covers the samples at rest, or drop the Coulomb columns (coulomb=False)")
            parameters: tuple[str, ...] = ("omega", "coulomb")
        elif set(involved) & set(_COULOMB_HINT):
            msg += ("; the trial has motion in one direction only: drop the Coulomb columns "
                    "(coulomb=False) or record a trial with reversals")
            parameters = ("coulomb",)
        else:
            msg += "; drop one of them or record a trial with richer excitation"
            parameters = ()
        raise ParameterError(msg, *parameters) if parameters else ValueError(msg)
    return Z, y, names


@dataclass(frozen=True)
class LSResult:
    """Least-squares fit ``y ≈ Zβ`` (method §3)."""

    beta: np.ndarray  # (m,)
    stderr: np.ndarray  # (m,) sqrt(diag(cov))
    cov: np.ndarray  # (m, m) σ̂² (ZᵀZ)⁻¹
    residuals: np.ndarray  # (N,) y − Zβ
    rmse: float  # sqrt(mean(residuals²))
    sigma2: float  # σ̂² = RSS / (N − m)
    names: tuple[str, ...]
    n_samples: int

    @property
    def dof(self) -> int:
        """Residual degrees of freedom ``N − m``."""
        return self.n_samples - self.beta.size

    def predict(self, Z) -> np.ndarray:
        """``Zβ`` for new regressors."""
        return np.asarray(Z, dtype=np.float64) @ self.beta


def least_squares(Z, y, names=None) -> LSResult:
    """Least-squares estimate of β (method §3, thesis eq. 2.8) via QR of the column-scaled ``Z``.

    Parameters
    ----------
    Z : array (N, m)
        Regressors (e.g. ``Regression.Z`` of :func:`kernels.feed_drive.regressors`).
    y : array (N,)
        Outputs ``y(k) = v_m(k+1)``.
    names : sequence of str, optional
        Column names, used in error messages (``Regression.names``).

    Returns
    -------
    LSResult
        ``beta``, classical ``stderr``/``cov`` = ``σ̂² (ZᵀZ)⁻¹`` (from ``R⁻¹R⁻ᵀ``, never by
        inverting ``ZᵀZ``), ``residuals = y − Zβ``, ``rmse``, ``sigma2 = RSS/(N − m)``.
    """
    Z, y, names = validate_regression(Z, y, names, intercept=False)
    n, m = Z.shape
    scale = np.sqrt(np.sum(Z * Z, axis=0))
    Q, R = np.linalg.qr(Z / scale)
    beta_s = solve_triangular(R, Q.T @ y)
    beta = beta_s / scale
    residuals = y - Z @ beta
    rss = float(residuals @ residuals)
    sigma2 = rss / (n - m)
    Rinv = solve_triangular(R, np.eye(m))
    cov = sigma2 * (Rinv @ Rinv.T) / np.outer(scale, scale)
    cov = 0.5 * (cov + cov.T)
    return LSResult(beta=beta, stderr=np.sqrt(np.diag(cov)), cov=cov, residuals=residuals,
                    rmse=math.sqrt(rss / n), sigma2=sigma2, names=names, n_samples=n)
