"""kernels.toeplitz and kernels.levinson: FFT products, circulant preconditioners, PCG, automatic choice;
Levinson–Durbin whitening, log-det and solves, exact and of order m."""

import numpy as np
import pytest
from scipy.linalg import toeplitz

from kernels.covariance import LocallyPeriodic, Periodic, SquaredExponential
from kernels.levinson import levinson_solve, levinson_whiten, toeplitz_logdet
from kernels.toeplitz import (
    SymmetricToeplitz,
    ToeplitzSolver,
    pcg,
    solve_spd_toeplitz,
    strang_eigenvalues,
    tchan_eigenvalues,
)

TS = 1.0 / 333.0


def column(kernel, n, gamma=50.0):
    t = kernel.lag(np.arange(n) * TS)
    t[0] += 1.0 / gamma
    return t


KERNELS = [
    LocallyPeriodic(0.59, 0.42, 1 / 55),
    SquaredExponential(0.05),
    Periodic(0.8, 1 / 50) * SquaredExponential(1.5),
]


@pytest.mark.parametrize("n", [1, 2, 7, 100, 1001])
@pytest.mark.parametrize("kernel", [KERNELS[0], SquaredExponential(0.02)], ids=["lp", "se-banded"])
def test_matvec_equals_dense(n, kernel):
    rng = np.random.default_rng(n)
    t = column(kernel, n)
    op = SymmetricToeplitz(t)
    assert op.size >= n + op.bandwidth and op.bandwidth <= max(n - 1, 0)
    A = toeplitz(t)
    x = rng.standard_normal(n)
    X = rng.standard_normal((n, 3))
    np.testing.assert_allclose(op.matvec(x), A @ x, rtol=0, atol=1e-12 * np.abs(A).sum(1).max())
    np.testing.assert_allclose(op @ X, A @ X, rtol=0, atol=1e-12 * np.abs(A).sum(1).max())
    np.testing.assert_allclose(op.to_dense(), A)


@pytest.mark.parametrize("kernel,n", [(KERNELS[0], 1600), (KERNELS[0], 2400), (KERNELS[1], 1700), (KERNELS[2], 1700)],
                         ids=["lp-1600", "lp-2400", "se-1700", "product-1700"])
def test_pcg_solve_equals_dense(kernel, n):
    t = column(kernel, n)
    rng = np.random.default_rng(0)
    B = rng.standard_normal((n, 3))
    solver = ToeplitzSolver(t, tol=1e-13, dense_limit=0)
    assert solver.method.startswith("pcg-")
    X = solver.solve(B)
    X_ref = np.linalg.solve(toeplitz(t), B)
    assert np.linalg.norm(X - X_ref) / np.linalg.norm(X_ref) < 1e-10
    x1 = solver.solve(B[:, 0])
    assert x1.shape == (n,)
    assert np.linalg.norm(x1 - X_ref[:, 0]) / np.linalg.norm(X_ref[:, 0]) < 1e-10
    assert solver.iterations > 0 and solver.residual <= 1e-11


def test_strang_not_positive_definite_falls_back_to_tchan():
    n = 1800
    record = n * TS
    kernel = LocallyPeriodic(10.0 * record, 0.42, 1 / 55)
    t = column(kernel, n)
    assert strang_eigenvalues(t).min() <= 0.0  # the detected failure
    assert tchan_eigenvalues(t).min() > 0.0
    solver = ToeplitzSolver(t, tol=1e-13, dense_limit=0)
    assert solver.method == "pcg-tchan"
    b = np.random.default_rng(1).standard_normal(n)
    x = solver.solve(b)
    x_ref = np.linalg.solve(toeplitz(t), b)
    assert np.linalg.norm(x - x_ref) / np.linalg.norm(x_ref) < 1e-10
    with pytest.raises(ValueError, match="Strang preconditioner is not positive definite"):
        ToeplitzSolver(t, dense_limit=0, preconditioner="strang")


def test_short_sigma1_uses_strang_and_small_n_dense():
    t = column(KERNELS[0], 3000)
    assert ToeplitzSolver(t, dense_limit=0).method == "pcg-strang"
    small = ToeplitzSolver(column(KERNELS[0], 800))
    assert small.method == "dense"
    b = np.ones(800)
    np.testing.assert_allclose(small.solve(b), np.linalg.solve(toeplitz(column(KERNELS[0], 800)), b), rtol=1e-10)
    np.testing.assert_allclose(solve_spd_toeplitz(column(KERNELS[0], 800), b), small.solve(b))


def test_tchan_forced_and_pcg_generic():
    t = column(KERNELS[1], 2000)
    solver = ToeplitzSolver(t, dense_limit=0, preconditioner="tchan", tol=1e-13)
    assert solver.method == "pcg-tchan"
    b = np.sin(np.arange(2000) / 17.0)
    x_ref = np.linalg.solve(toeplitz(t), b)
    assert np.linalg.norm(solver.solve(b) - x_ref) / np.linalg.norm(x_ref) < 1e-10
    # unpreconditioned CG on the same operator, zero right-hand side column handled
    op = SymmetricToeplitz(t)
    res = pcg(op.matvec_rows, np.column_stack([b, np.zeros(2000)]), tol=1e-12, max_iter=5000)
    assert res.converged
    np.testing.assert_array_equal(res.x[:, 1], 0.0)
    assert np.linalg.norm(res.x[:, 0] - x_ref) / np.linalg.norm(x_ref) < 1e-9


@pytest.mark.parametrize("kernel", KERNELS + [LocallyPeriodic(30.0, 0.42, 1 / 55)], ids=str)
def test_levinson_logdet_equals_slogdet(kernel):
    t = column(kernel, 900)
    sign, ref = np.linalg.slogdet(toeplitz(t))
    assert sign == 1.0
    assert toeplitz_logdet(t) == pytest.approx(ref, rel=1e-10, abs=1e-8)
    assert toeplitz_logdet(t * 7.0) == pytest.approx(ref + 900 * np.log(7.0), rel=1e-10)


@pytest.mark.parametrize("kernel, gamma", [(KERNELS[0], 50.0), (SquaredExponential(0.003), 1e3),
                                           (LocallyPeriodic(30.0, 0.05, 1 / 55), 1e6)], ids=["lp", "se-short", "lp-long-stiff"])
def test_levinson_solve_and_whiten_equal_dense(kernel, gamma):
    """A⁻¹B and L⁻¹B by Levinson–Durbin, whatever the conditioning (σ1 ≫ record, γ = 1e6), and for a
    short kernel whose predictor would decay into subnormal numbers."""
    n = 700
    t = column(kernel, n, gamma)
    A = toeplitz(t)
    B = np.random.default_rng(3).normal(size=(n, 3))
    X = levinson_solve(t, B)
    ref = np.linalg.solve(A, B)
    assert np.linalg.norm(X - ref) / np.linalg.norm(ref) < 1e-7 * max(1.0, gamma / 1e3)
    np.testing.assert_allclose(levinson_solve(t, B[:, 0]), X[:, 0])
    w = levinson_whiten(t, B)
    assert w.exact and w.order == n - 1
    L = np.linalg.cholesky(A)
    np.testing.assert_allclose(w.white, np.linalg.solve(L, B), rtol=1e-6, atol=1e-7 * np.abs(w.white).max())
    assert w.logdet == pytest.approx(np.linalg.slogdet(A)[1], rel=1e-9, abs=1e-6)


def test_order_m_is_the_exact_algebra_of_a_valid_covariance():
    """Order m (eq. V2): rows ≤ m exact, later rows whitened by the order-m predictor (FFT). Its L̃⁻¹ built
    column by column gives Ã⁻¹ = L̃⁻ᵀL̃⁻¹, positive definite; the solve and log|Ã| match that matrix to
    rounding, and (V3) bounds how far log|Ã| lies above the exact log|A|."""
    n, m = 900, 300
    t = column(LocallyPeriodic(0.3, 0.5, 0.02), n)
    B = np.random.default_rng(5).normal(size=(n, 3))
    L_inv = levinson_whiten(t, np.eye(n), max_order=m).white        # columns of L̃⁻¹
    A_inv = L_inv.T @ L_inv
    w = levinson_whiten(t, B, max_order=m)
    assert w.order == m and not w.exact
    np.testing.assert_allclose(w.white, L_inv @ B, rtol=1e-10, atol=1e-12)
    exact = levinson_whiten(t, B)
    np.testing.assert_allclose(w.white[: m + 1], exact.white[: m + 1], rtol=1e-10, atol=1e-12)
    assert w.logdet == pytest.approx(-np.linalg.slogdet(A_inv)[1], rel=1e-10)
    assert 0.0 <= w.logdet - exact.logdet
    X = levinson_solve(t, B, m)
    np.testing.assert_allclose(X, A_inv @ B, rtol=1e-9, atol=1e-12 * np.abs(X).max())
    np.testing.assert_allclose(levinson_solve(t, B, n), np.linalg.solve(toeplitz(t), B), rtol=1e-8)


@pytest.mark.parametrize("kernel, gamma", [(LocallyPeriodic(0.3, 0.5, 0.02), 50.0), (SquaredExponential(0.05), 1e3),
                                           (LocallyPeriodic(30.0, 0.05, 1.0), 1e6)], ids=["lp", "se", "sharp-long-period"])
def test_the_stop_criterion_bounds_the_log_det_error(kernel, gamma):
    """The order chosen by the criterion (V3) leaves log|A| within a few ``tol`` of the exact value; a kernel
    that is ~0 between the multiples of a long period (ψ = 333 samples) is not stopped inside its support,
    and an order bounded below what the data need says so in its tail estimate."""
    n = 4000
    t = column(kernel, n, gamma)
    exact = levinson_whiten(t, np.zeros((n, 0))).logdet
    tol = 0.5
    support = int(np.flatnonzero(np.abs(t) > 1e-3 * t[0])[-1])
    w = levinson_whiten(t, np.zeros((n, 0)), tol=tol, min_order=support)
    assert w.order >= min(support, n - 1)
    assert 0.0 <= w.logdet - exact < 4 * tol + 1e-9
    if w.order > 1000:
        bounded = levinson_whiten(t, np.zeros((n, 0)), tol=tol, max_order=1000, min_order=support)
        assert bounded.order == 1000 and bounded.tail_estimate > tol and bounded.logdet - exact > tol


def test_not_positive_definite_is_reported():
    with pytest.raises(ValueError, match="not positive definite"):
        toeplitz_logdet(np.array([1.0, 2.0, 0.0]))
    with pytest.raises(ValueError, match="not positive definite"):
        ToeplitzSolver(np.array([1.0, 2.0, 0.0]))
    with pytest.raises(ValueError, match="not positive definite"):
        levinson_solve(np.array([1.0, 2.0, 0.0]), np.ones(3))
    with pytest.raises(ValueError, match="non-finite value at lag 1"):
        SymmetricToeplitz([1.0, np.nan])
