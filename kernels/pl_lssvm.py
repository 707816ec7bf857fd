"""Partially linear LS-SVM identification (method §4, thesis eq. 2.9–2.12).

Model ``y(k) = βᵀz(k) + f(x(k)) + ε(k)`` (eq. 2.5). The KKT system of eq. 2.9,

    [ A    1   Z ] [α]   [y]
    [ 1ᵀ   0   0 ] [c] = [0]        A = Ω + γ⁻¹I,  Ω_ij = k(x_i, x_j)   (eq. 2.10)
    [ Zᵀ   0   0 ] [β]   [0]

is solved by eliminating α: with ``Z̃ = [1, Z]``,
``[c; β] = (Z̃ᵀA⁻¹Z̃)⁻¹ Z̃ᵀA⁻¹y`` and ``α = A⁻¹(y − Z̃[c; β])``. Only solves with ``A``
are needed:

* time kernels on a uniform grid (``x`` = sample times, or ``Ts``): ``A`` is SPD Toeplitz;
  :class:`kernels.toeplitz.ToeplitzSolver` (FFT-PCG with a Strang or T. Chan circulant
  preconditioner, dense Cholesky for small N) — ``O(N log N)`` per iteration, ``O(N)`` memory —
  or Levinson–Durbin (:func:`kernels.levinson.levinson_solve`, exact in ``O(N²)``, whatever the
  conditioning; with ``order``: the order-m approximation of the likelihood, ``O(m² + N log m)``).
  ``solver="auto"``: dense Cholesky up to ``toeplitz_dense_limit`` samples, else
  PCG, falling back to Levinson (up to ``LEVINSON_LIMIT`` samples) when PCG does not converge
  (long σ1 with large γ: thousands of iterations).
* vector inputs ``x`` (N, d): dense Cholesky of ``A``, limited to ``dense_limit`` samples.
* the spindle-phase kernel on ``(t, θ)`` with the stretches of constant spindle speed ``phase``
  (:mod:`kernels.spindle_phase`), and a gate (the disturbance acts only where a process acts,
  :mod:`kernels.blocks`): block-diagonal ``A``, Levinson–Durbin per stretch (eq. S2, B1).

Uncertainty: in the Gaussian-process reading of :mod:`kernels.likelihood` (eq. L1) ``[c; β]`` is
the GLS estimate and its covariance is ``ŝ² (Z̃ᵀA⁻¹Z̃)⁻¹`` with ``ŝ² = rᵀA⁻¹r/(N − p)``,
``r = y − Z̃[c; β]`` (eq. L3); :attr:`PLLSSVMResult.cov` and ``stderr``.

Numerics: the (p × p) generalised-least-squares system is solved on unit-norm-scaled columns
(β entries differ by orders of magnitude: Coulomb columns ±1, velocities 1e-2 m/s) and refined
once: ``α₁ = A⁻¹(y − Z̃b₀)`` is solved on the (small) residual, the KKT constraint
``Z̃ᵀα = 0`` gives the correction ``Δb = (Z̃ᵀA⁻¹Z̃)⁻¹Z̃ᵀα₁``, ``α = α₁ − A⁻¹Z̃ Δb``. Because the
correction uses the exact ``A``, the first (p+1 right-hand sides) PCG solve runs at the looser
``FIRST_TOL`` and only the single refinement solve at ``tol``.

The disturbance estimate (eq. 2.12) ``f = Ωα + c`` is computed without a product with Ω:
``Ωα = Aα − α/γ = y − Z̃[c; β] − α/γ``, hence ``f = y − Zβ − α/γ`` (more accurate than
forming ``Ωα`` because the PCG residual does not enter it).

Force-input form: ``z`` already holds a constant column (``one``, the force offset). Then
``c`` and the offset coefficient are the same parameter; the separate bias is dropped (the
constraint ``1ᵀα = 0`` is contained in ``Zᵀα = 0``) and ``c = 0`` is reported.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve

from .blocks import blocks
from .covariance import Kernel
from .least_squares import validate_regression
from .levinson import levinson_solve
from .spindle_phase import PhaseSegments
from .toeplitz import DENSE_LIMIT as TOEPLITZ_DENSE_LIMIT
from .toeplitz import WARN_FACTOR, ToeplitzSolver

__all__ = ["PLLSSVMResult", "pl_lssvm", "PL_DENSE_LIMIT", "LEVINSON_LIMIT", "GRID_RTOL", "time_grid",
           "constant_column", "prepare_regression", "gls_solve"]

#: Largest N for the dense path (vector inputs): the N×N matrix takes 8 N² bytes (0.5 GB at 8000).
PL_DENSE_LIMIT = 8000
#: Largest N for the Levinson path (``O(N²)``: ~4 s at 25 000 samples, ~25 s at 60 000).
LEVINSON_LIMIT = 60000
#: PCG iterations tried by ``solver="auto"`` before it falls back to Levinson.
AUTO_PCG_ITERATIONS = 400
#: A step of the time grid may differ from Ts by this fraction before it counts as a gap.
GRID_RTOL = 0.01


@dataclass(frozen=True)
class PLLSSVMResult:
    """PL-LSSVM fit (method §4).

    ``f`` is the disturbance estimate ``Ωα + c`` (eq. 2.12, velocity units), ``residuals`` the
    model error ``y − Zβ − f = α/γ`` (the ``e_k`` of the LS-SVM), ``linear_residuals``
    ``y − Zβ`` (what the online tracker sees, method §6).
    """

    beta: np.ndarray  # (m,)
    c: float  # bias of eq. 2.9 (0 when Z has its own constant column)
    alpha: np.ndarray  # (N,) Lagrange multipliers
    f: np.ndarray  # (N,) disturbance estimate Ωα + c
    residuals: np.ndarray  # (N,) y − Zβ − f = α/γ
    linear_residuals: np.ndarray  # (N,) y − Zβ
    rmse: float  # sqrt(mean(residuals²))
    solver: str  # 'toeplitz-pcg-strang' | 'toeplitz-pcg-tchan' | 'toeplitz-dense' | 'toeplitz-levinson' | 'dense'
    iterations: int  # PCG iterations (max over right-hand sides, summed over both solves); 0 for dense
    names: tuple[str, ...]
    gamma: float
    kernel: Kernel
    Ts: float | None  # grid step of the Toeplitz path, None for the dense path
    pcg_residual: float  # largest relative residual of the PCG solves (0 for dense)
    cov: np.ndarray | None = None  # (m, m) GLS covariance of β, ŝ² (Z̃ᵀA⁻¹Z̃)⁻¹ (eq. L3)
    s2: float = math.nan  # ŝ² = rᵀA⁻¹r / (N − p)

    @property
    def stderr(self) -> np.ndarray:
        """Standard errors of β (square roots of the diagonal of :attr:`cov`)."""
        return np.sqrt(np.maximum(np.diag(self.cov), 0.0))


def constant_column(Z) -> int | None:
    """Index of a non-zero constant column of ``Z`` (the force-input ``one``), else None."""
    Z = np.asarray(Z)
    if Z.ndim != 2 or Z.shape[0] == 0:
        return None
    for j in range(Z.shape[1]):
        col = Z[:, j]
        if col[0] != 0.0 and np.all(col == col[0]):
            return j
    return None


def time_grid(x, n: int, Ts: float | None) -> float:
    """Grid step of sample times ``x`` (length ``n``); ``ValueError`` naming the first gap.

    With ``Ts`` given, every step must equal it (within ``GRID_RTOL``); otherwise the mean step
    ``(x[-1] − x[0])/(n − 1)`` is used.
    """
    t = np.asarray(x, dtype=np.float64).reshape(-1)
    if t.size != n:
        raise ValueError(f"x has {t.size} sample times but Z has {n} rows; x(k) must align with z(k)")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise ValueError(f"x has {bad.size} non-finite value(s), first at sample {bad[0]}")
    dt = np.diff(t)
    nonpos = np.flatnonzero(dt <= 0)
    if nonpos.size:
        k = int(nonpos[0])
        raise ValueError(f"sample times must increase: x[{k + 1}] = {t[k + 1]!r} s follows x[{k}] = {t[k]!r} s; "
                         "sort the trial or remove duplicated samples")
    step = float(Ts) if Ts is not None else (t[-1] - t[0]) / (n - 1)
    off = np.flatnonzero(np.abs(dt - step) > GRID_RTOL * step)
    if off.size:
        k = int(off[0])
        raise ValueError(
            f"sample times are not on a uniform grid: the step from sample {k} to {k + 1} is {dt[k]:.6g} s "
            f"but Ts = {step:.6g} s ({off.size} irregular step(s)). The Toeplitz solver for time kernels needs "
            "uniform sampling: resample the trial onto a uniform grid, or split it at the gap and identify "
            "the pieces separately")
    return step


def prepare_regression(Z, y, names=None):
    """Validate (shared :func:`kernels.least_squares.validate_regression`) and build ``Z̃``.

    Returns ``(Z, y, names, Z_tilde, intercept)``; ``Z̃ = [1, Z]`` unless ``Z`` already has a
    constant column (force-input ``one``), in which case ``Z̃ = Z`` and ``intercept`` is False.
    """
    Z_arr = np.asarray(Z, dtype=np.float64)
    if Z_arr.ndim == 1:
        Z_arr = Z_arr[:, None]
    const = constant_column(Z_arr) if Z_arr.ndim == 2 and np.all(np.isfinite(Z_arr)) else None
    intercept = const is None
    Z_arr, y, names = validate_regression(Z_arr, y, names, intercept=intercept)
    Zt = np.column_stack([np.ones(Z_arr.shape[0]), Z_arr]) if intercept else Z_arr
    return Z_arr, y, names, Zt, intercept


def _check_gamma(gamma) -> float:
    g = float(gamma)
    if not (math.isfinite(g) and g > 0):
        raise ValueError(f"regularisation gamma must be a positive finite number, got {gamma!r}")
    return g


def _dense_kernel_matrix(kernel: Kernel, X: np.ndarray, shift: float, block: int = 1024) -> np.ndarray:
    """``Ω + shift·I`` built in row blocks (limits temporaries to block × N)."""
    n = X.shape[0]
    A = np.empty((n, n))
    for i in range(0, n, block):
        A[i:i + block] = kernel(X[i:i + block], X)
    A[np.diag_indices(n)] += shift
    return A


#: Solvers of :func:`pl_lssvm` (time kernels; vector inputs always use the dense path).
SOLVERS = ("auto", "pcg", "levinson")

#: PCG tolerance of the first, (p+1)-right-hand-side solve. The refinement solve (tolerance ``tol``) on
#: the residual removes its effect on b: g = Z̃ᵀA⁻¹(y − Z̃b₀) = M(b − b₀) uses the exact A, and an
#: approximate M only slows the (one-step) correction by a factor ~FIRST_TOL·κ.
FIRST_TOL = 1e-8


class _LevinsonSolver:
    """``A⁻¹B`` by Levinson–Durbin (exact, ``O(N²)`` per right-hand side), or of the order-m
    approximation (:mod:`kernels.levinson`, ``O(m² + N log m)``) when ``order`` is given."""

    def __init__(self, column: np.ndarray, order: int | None = None):
        self.column = column
        self.order = order
        self.iterations = 0
        self.residual = 0.0

    def solve(self, B, tol=None):
        return levinson_solve(self.column, B, self.order)


class _BlockSolver:
    """``A⁻¹B`` for a block-diagonal ``A`` (:mod:`kernels.blocks`: stretches of constant spindle speed, a
    gate): Levinson–Durbin per Toeplitz block (of order ≤ ``order`` when given), ``γB`` where the gate is
    closed."""

    def __init__(self, parts, gamma: float, order: int | None = None):
        self.parts = parts
        self.gamma = gamma
        self.order = order
        self.iterations = 0
        self.residual = 0.0

    def solve(self, B, tol=None):
        B = np.asarray(B, dtype=np.float64)
        out = np.empty_like(B)
        for part in self.parts:
            a, b = part.start, part.stop
            if not part.kept:  # left out of the fit: infinite variance
                out[a:b] = 0.0
            elif part.column is None:
                out[a:b] = self.gamma * B[a:b]
            else:
                order = None if self.order is None or b - a <= 1 else min(self.order, b - a - 1)
                out[a:b] = levinson_solve(part.column, B[a:b], order)
        return out


class _DenseSolver:
    def __init__(self, A: np.ndarray):
        try:
            self._chol = cho_factor(A, lower=True, overwrite_a=True, check_finite=False)
        except LinAlgError:
            raise ValueError("Ω + I/γ is not positive definite (Cholesky failed): the kernel is not a valid "
                             "covariance for these inputs or γ is too large; lower γ") from None
        self.iterations = 0
        self.residual = 0.0

    def solve(self, B, tol=None):
        return cho_solve(self._chol, B, check_finite=False)


def _setup_solver(kernel, gamma, n, x, Ts, tol, max_iter, dense_limit, toeplitz_dense_limit, method="auto",
                  order=None):
    """Pick the path of method §4; returns (solver, name, Ts or None)."""
    if method not in SOLVERS:
        raise ValueError(f"solver must be one of {', '.join(SOLVERS)}, got {method!r}")
    if not isinstance(kernel, Kernel):
        raise ValueError(f"kernel must be a kernels.covariance.Kernel, got {type(kernel).__name__}")
    time_kernel = kernel.is_stationary_1d
    if x is None:
        if Ts is None:
            raise ValueError("give x (sample times in s, or input vectors (N, d)) or Ts (sample period of a "
                             "uniform time grid)")
        if not time_kernel:
            raise ValueError(f"{kernel!r} reads vector inputs: pass x of shape (N, d); Ts alone only describes time")
        Ts = float(Ts)
        if not (math.isfinite(Ts) and Ts > 0):
            raise ValueError(f"Ts must be a positive sample period in s, got {Ts!r}")
        step = Ts
    else:
        X = np.asarray(x, dtype=np.float64)
        if X.ndim == 1 or (X.ndim == 2 and X.shape[1] == 1 and time_kernel):
            if not time_kernel:
                X = X.reshape(-1, 1)
                step = None
            else:
                step = time_grid(X, n, Ts)
        else:
            step = None
        if step is None:
            if X.ndim != 2 or X.shape[0] != n:
                raise ValueError(f"x must have one row per sample of Z ({n}), got shape {X.shape}")
            bad_rows = np.flatnonzero(~np.all(np.isfinite(X), axis=1))
            if bad_rows.size:
                raise ValueError(f"x has non-finite values, first at sample {bad_rows[0]}")
            if n > dense_limit:
                gb = 8.0 * n * n / 1e9
                raise ValueError(
                    f"PL-LSSVM with vector inputs x (shape {X.shape}) needs the dense N×N kernel matrix: "
                    f"N = {n} exceeds dense_limit = {dense_limit} (it would take {gb:.1f} GB). Use a time kernel "
                    "on a uniform grid (x = sample times, or Ts), which runs in O(N log N), or fewer samples "
                    "(a shorter or decimated segment)")
            return _DenseSolver(_dense_kernel_matrix(kernel, X, 1.0 / gamma)), "dense", None
    column = kernel.lag(np.arange(n if method != "levinson" or order is None else min(n, order + 1)) * step)
    column[0] += 1.0 / gamma
    if method == "levinson":
        approx = order is not None and order < n - 1
        return _LevinsonSolver(column, order), f"toeplitz-levinson-ar{order}" if approx else "toeplitz-levinson", step
    if method == "auto" and max_iter is None and n > toeplitz_dense_limit:
        max_iter = AUTO_PCG_ITERATIONS
    solver = ToeplitzSolver(column, tol=tol, max_iter=max_iter, dense_limit=toeplitz_dense_limit)
    name = "toeplitz-dense" if solver.method == "dense" else f"toeplitz-{solver.method}"
    return solver, name, step


def gls_solve(solver, Zt: np.ndarray, y: np.ndarray):
    """``b = (Z̃ᵀA⁻¹Z̃)⁻¹Z̃ᵀA⁻¹y``, ``α = A⁻¹(y − Z̃b)`` with one refinement step (module docstring).

    Returns ``(b, alpha, W, M_scaled_cho, scale, iterations, pcg_residual, converged)`` where
    ``W = A⁻¹Z̃``, ``scale`` the column norms of ``Z̃``, ``M_scaled_cho`` the Cholesky factor of
    ``D Z̃ᵀA⁻¹Z̃ D`` (``D = diag(1/scale)``) and ``converged`` whether both solves reached their
    tolerance (within ``WARN_FACTOR``).
    """
    p = Zt.shape[1]
    scale = np.sqrt(np.sum(Zt * Zt, axis=0))
    tol = getattr(solver, "tol", 0.0)
    first_tol = max(tol, FIRST_TOL)
    S = solver.solve(np.column_stack([Zt, y]), tol=first_tol)
    iterations, resid = solver.iterations, solver.residual
    converged = resid <= WARN_FACTOR * first_tol
    W, u = S[:, :p], S[:, p]
    Ms = (Zt.T @ W) / np.outer(scale, scale)
    Ms = 0.5 * (Ms + Ms.T)
    try:
        cho = cho_factor(Ms, lower=True, check_finite=False)
    except LinAlgError:
        raise ValueError("Z̃ᵀ(Ω + I/γ)⁻¹Z̃ is singular: the regressors are (numerically) dependent once the "
                         "kernel part is accounted for; drop a column or lower γ") from None
    b = cho_solve(cho, (Zt.T @ u) / scale, check_finite=False) / scale
    # refinement on the residual (small compared with y)
    alpha = solver.solve(y - Zt @ b)
    iterations += solver.iterations
    converged = converged and solver.residual <= WARN_FACTOR * tol
    resid = max(resid, solver.residual)
    db = cho_solve(cho, (Zt.T @ alpha) / scale, check_finite=False) / scale
    b = b + db
    alpha = alpha - W @ db
    return b, alpha, W, cho, scale, iterations, resid, converged


def pl_lssvm(Z, y, kernel: Kernel, gamma: float, *, x=None, Ts: float | None = None, names=None,
             tol: float = 1e-12, max_iter: int | None = None, dense_limit: int = PL_DENSE_LIMIT,
             toeplitz_dense_limit: int = TOEPLITZ_DENSE_LIMIT, solver: str = "auto",
             phase: PhaseSegments | None = None, order: int | None = None, gate=None,
             keep=None) -> PLLSSVMResult:
    """PL-LSSVM estimate of β and the disturbance ``f`` (method §4, thesis eq. 2.9–2.12).

    Parameters
    ----------
    Z : array (N, m)
        Regressors ``z(k)`` (``Regression.Z``).
    y : array (N,)
        Outputs ``y(k) = v_m(k+1)``.
    kernel : Kernel
        Covariance function (method §5), e.g. ``LocallyPeriodic(σ1, σ2, ψ)`` on time.
    gamma : float
        Regularisation γ (``A = Ω + γ⁻¹I``).
    x : array (N,) or (N, d), optional
        Kernel inputs aligned with the rows of Z: sample times (s) for a time kernel — they must
        lie on a uniform grid — or input vectors (dense path).
    Ts : float, optional
        Sample period (s) of a uniform time grid, when ``x`` is not given.
    names : sequence of str, optional
        Column names for error messages (``Regression.names``).
    tol, max_iter :
        PCG relative residual target and iteration limit (Toeplitz path).
    dense_limit : int
        Largest N accepted on the dense (vector-input) path.
    toeplitz_dense_limit : int
        Time kernels with ``N ≤`` this use a dense Cholesky of the Toeplitz matrix (``solver="auto"``).
    solver : "auto", "pcg" or "levinson"
        Path for time kernels (module docstring); "pcg" honours ``toeplitz_dense_limit`` too.
    order : int, optional
        With ``solver="levinson"`` (and the spindle-phase path): the order-m approximation of
        :mod:`kernels.levinson` (exact when None or ``≥ N − 1``), the one the likelihood used.
    gate : array (N,) of bool, optional
        Where the disturbance acts (eq. B1 of :mod:`kernels.blocks`; time kernels and the spindle-phase
        path): block-diagonal solves, ``f = 0`` where it is False.
    keep : array (N,) of bool, optional
        The samples in the fit; where it is False ``α = 0`` and ``f`` is NaN (not estimated).
    phase : PhaseSegments, optional
        Stretches of constant spindle speed: ``kernel`` is then a kernel on ``(t, θ)`` (the
        spindle-phase kernel), solved block-diagonally on a grid of period ``Ts``.

    Raises
    ------
    ValueError
        Non-finite inputs, too few samples, rank-deficient ``Z`` (naming the columns; e.g. no speed
        reversal), non-uniform time grid (naming the gap), N above ``dense_limit`` on the dense path.
    """
    gamma = _check_gamma(gamma)
    Z_arr, y, names, Zt, intercept = prepare_regression(Z, y, names)
    n, p = Zt.shape
    method = solver
    if phase is not None or gate is not None or keep is not None:
        if Ts is None or (phase is not None and phase.edges[-1] != n):
            raise ValueError(f"the spindle-phase and gated paths need Ts and stretches covering the {n} samples")
        parts = blocks(kernel, gamma, float(Ts), n, gate=gate, phase=phase, max_order=order, keep=keep)
        name = f"spindle-{phase.count}" if phase is not None else f"gated-{sum(b.column is not None for b in parts)}"
        solver, solver_name, step = _BlockSolver(parts, gamma, order), name, float(Ts)
    else:
        solver, solver_name, step = _setup_solver(kernel, gamma, n, x, Ts, tol, max_iter, dense_limit,
                                                  toeplitz_dense_limit, method, order)
    fallback = method == "auto" and max_iter is None and solver_name.startswith("toeplitz-pcg") and n <= LEVINSON_LIMIT
    with warnings.catch_warnings():
        if fallback:
            warnings.simplefilter("ignore", RuntimeWarning)  # checked below: Levinson takes over
        b, alpha, _, cho, scale, iterations, resid, converged = gls_solve(solver, Zt, y)
    if fallback and not converged:
        solver, solver_name = _LevinsonSolver(solver.column), "toeplitz-levinson"
        b, alpha, _, cho, scale, iterations, resid, _ = gls_solve(solver, Zt, y)
    c, beta = (float(b[0]), b[1:]) if intercept else (0.0, b)
    linear = y - Z_arr @ beta
    residuals = alpha / gamma
    f = linear - residuals  # where a gate is closed A = I/γ: α/γ is the whole residual, f = c
    if keep is not None:
        f = np.where(np.asarray(keep, dtype=bool), f, np.nan)
    n_fit = n if keep is None else int(np.sum(keep))
    s2 = float((y - Zt @ b) @ alpha) / (n_fit - p)
    Minv = cho_solve(cho, np.eye(p), check_finite=False) / np.outer(scale, scale)
    cov = s2 * 0.5 * (Minv + Minv.T)
    return PLLSSVMResult(beta=beta, c=c, alpha=alpha, f=f, residuals=residuals, linear_residuals=linear,
                         rmse=math.sqrt(float(residuals @ residuals) / n), solver=solver_name,
                         iterations=int(iterations), names=names, gamma=gamma, kernel=kernel, Ts=step,
                         pcg_residual=float(resid), cov=cov[1:, 1:] if intercept else cov, s2=s2)
