"""kernels.pl_lssvm: equality with the dense KKT solve of method §4, bias removal, errors."""

import numpy as np
import pytest

from kernels.covariance import LocallyPeriodic, Product, SquaredExponential
from kernels.errors import ParameterError
from kernels.least_squares import least_squares
from kernels.pl_lssvm import pl_lssvm
from replay.streams import shaker_stream, simulate

THESIS_KERNEL = LocallyPeriodic(0.59, 0.42, 1 / 55)
GAMMA = 50.3


def dense_kkt(Z, y, Omega, gamma, intercept=True):
    """Reference: the (N+1+m) KKT system of method §4 (eq. 2.9), columns of Z equilibrated."""
    n, m = Z.shape
    s = np.sqrt(np.sum(Z * Z, axis=0))
    Zs = Z / s
    cols = ([np.ones((n, 1))] if intercept else []) + [Zs]
    C = np.hstack(cols)
    p = C.shape[1]
    K = np.zeros((n + p, n + p))
    K[:n, :n] = Omega + np.eye(n) / gamma
    K[:n, n:] = C
    K[n:, :n] = C.T
    sol = np.linalg.solve(K, np.concatenate([y, np.zeros(p)]))
    alpha = sol[:n]
    c = sol[n] if intercept else 0.0
    beta = sol[n + (1 if intercept else 0):] / s
    return beta, c, alpha, Omega @ alpha + c


def rel(a, b):
    return np.linalg.norm(np.asarray(a) - b) / np.linalg.norm(b)


@pytest.mark.parametrize("form", ["velocity-loop", "force-input"])
@pytest.mark.parametrize("path", ["toeplitz-pcg-strang", "toeplitz-dense"])
def test_toeplitz_path_equals_dense_kkt(form, path):
    n = 1601 if path == "toeplitz-pcg-strang" else 1401
    kw = {"offset": 2.0} if form == "force-input" else {}
    s = shaker_stream(n, amplitude=10.0, seed=7, form=form, **kw)
    reg = s.regression()
    res = pl_lssvm(reg.Z, reg.y, THESIS_KERNEL, GAMMA, x=s.x, names=reg.names,
                   toeplitz_dense_limit=0 if path == "toeplitz-pcg-strang" else 1500)
    assert res.solver == path
    Omega = THESIS_KERNEL(s.x)
    beta, c, alpha, f = dense_kkt(reg.Z, reg.y, Omega, GAMMA, intercept=(form == "velocity-loop"))
    np.testing.assert_allclose(res.beta, beta, rtol=1e-8)
    assert rel(res.f, f) < 1e-8
    assert rel(res.alpha, alpha) < 1e-8
    assert res.c == pytest.approx(c, abs=1e-10)
    if form == "force-input":
        assert res.c == 0.0  # the 'one' column carries the constant (module docstring)
    np.testing.assert_allclose(res.residuals, reg.y - reg.Z @ res.beta - res.f, atol=1e-13)
    np.testing.assert_allclose(res.residuals, res.alpha / GAMMA, atol=1e-15)
    assert res.rmse == pytest.approx(np.sqrt(np.mean(res.residuals ** 2)))


@pytest.mark.parametrize("form", ["velocity-loop", "force-input"])
def test_dense_path_equals_dense_kkt(form):
    s = shaker_stream(1500, amplitude=10.0, seed=8, form=form)
    reg = s.regression()
    x = np.column_stack([s.x, reg.Z[:, 1]])  # time and measured velocity
    kernel = Product(LocallyPeriodic(0.59, 0.42, 1 / 55, dims=0), SquaredExponential(0.05, dims=1))
    res = pl_lssvm(reg.Z, reg.y, kernel, GAMMA, x=x)
    assert res.solver == "dense" and res.iterations == 0 and res.Ts is None
    beta, c, alpha, f = dense_kkt(reg.Z, reg.y, kernel(x), GAMMA, intercept=(form == "velocity-loop"))
    np.testing.assert_allclose(res.beta, beta, rtol=1e-8)
    assert rel(res.f, f) < 1e-8


def test_ts_only_equals_sample_times_and_tchan_path():
    s = shaker_stream(1700, amplitude=10.0, seed=9)
    reg = s.regression()
    a = pl_lssvm(reg.Z, reg.y, THESIS_KERNEL, GAMMA, Ts=s.Ts, toeplitz_dense_limit=0)
    b = pl_lssvm(reg.Z, reg.y, THESIS_KERNEL, GAMMA, x=s.x + 12.5, toeplitz_dense_limit=0)
    np.testing.assert_allclose(a.beta, b.beta, rtol=1e-10)
    long_kernel = LocallyPeriodic(10 * 1700 * s.Ts, 0.42, 1 / 55)
    c = pl_lssvm(reg.Z, reg.y, long_kernel, GAMMA, Ts=s.Ts, toeplitz_dense_limit=0, solver="pcg")
    assert c.solver == "toeplitz-pcg-tchan"
    beta, _, _, f = dense_kkt(reg.Z, reg.y, long_kernel(s.x), GAMMA)
    np.testing.assert_allclose(c.beta, beta, rtol=1e-8)
    assert rel(c.f, f) < 1e-8
    lev = pl_lssvm(reg.Z, reg.y, long_kernel, GAMMA, Ts=s.Ts, solver="levinson")
    assert lev.solver == "toeplitz-levinson" and lev.iterations == 0
    np.testing.assert_allclose(lev.beta, beta, rtol=1e-8)
    assert rel(lev.f, f) < 1e-8


def test_auto_falls_back_to_levinson_when_pcg_stalls():
    """Long σ1 with a large γ: PCG needs thousands of iterations; auto switches to the exact Levinson
    solve (no warning, same answer as the dense KKT system)."""
    s = shaker_stream(1700, amplitude=10.0, seed=9)
    reg = s.regression()
    kernel = LocallyPeriodic(100.0, 0.05, 1 / 55)
    res = pl_lssvm(reg.Z, reg.y, kernel, 1e6, Ts=s.Ts, toeplitz_dense_limit=0)
    assert res.solver == "toeplitz-levinson"
    beta, _, _, f = dense_kkt(reg.Z, reg.y, kernel(s.x), 1e6)
    np.testing.assert_allclose(res.beta, beta, rtol=1e-6)


def test_gls_covariance_is_that_of_the_gp_reading():
    """cov(β) = ŝ² (Z̃ᵀA⁻¹Z̃)⁻¹ with ŝ² = rᵀA⁻¹r/(N − p) (eq. L3), the same on every path."""
    s = shaker_stream(900, amplitude=10.0, seed=4)
    reg = s.regression()
    A = THESIS_KERNEL(s.x) + np.eye(s.x.size) / GAMMA
    Zt = np.column_stack([np.ones(s.x.size), reg.Z])
    M = Zt.T @ np.linalg.solve(A, Zt)
    b = np.linalg.solve(M, Zt.T @ np.linalg.solve(A, reg.y))
    r = reg.y - Zt @ b
    s2 = r @ np.linalg.solve(A, r) / (s.x.size - Zt.shape[1])
    ref = s2 * np.linalg.inv(M)[1:, 1:]
    for solver, limit in (("auto", 1500), ("pcg", 0), ("levinson", 0)):
        res = pl_lssvm(reg.Z, reg.y, THESIS_KERNEL, GAMMA, Ts=s.Ts, solver=solver, toeplitz_dense_limit=limit)
        np.testing.assert_allclose(res.cov, ref, rtol=1e-6)
        np.testing.assert_allclose(res.stderr, np.sqrt(np.diag(ref)), rtol=1e-6)
        assert res.s2 == pytest.approx(s2, rel=1e-8)


def test_shaker_stream_ls_biased_pl_lssvm_recovers_beta():
    """Thesis case-1-like trial: 55 Hz + 110 Hz shaker (10 N vs 20/25 N Coulomb friction)."""
    s = shaker_stream(2500, amplitude=10.0, seed=1)
    reg = s.regression()
    ls = least_squares(reg.Z, reg.y, reg.names)
    pl = pl_lssvm(reg.Z, reg.y, THESIS_KERNEL, GAMMA, x=s.x, names=reg.names)
    ls_err = np.abs(ls.beta[:2] - s.beta[:2]) / s.beta[:2]
    pl_err = np.abs(pl.beta[:2] - s.beta[:2]) / s.beta[:2]
    assert ls_err[1] > 0.02, ls_err  # LS: β2 biased by more than 2 %
    assert ls_err[1] > 10 * pl_err[1]
    assert np.all(pl_err < 0.005), pl_err  # PL-LSSVM: β1, β2 within 0.5 %
    assert np.corrcoef(pl.f, s.f)[0, 1] > 0.99  # the disturbance estimate follows −b T_c
    assert pl.solver == "toeplitz-pcg-strang"


def test_errors():
    s = shaker_stream(1600, amplitude=10.0, seed=2)
    reg = s.regression()
    x = s.x.copy()
    x[900:] += 5 * s.Ts
    with pytest.raises(ValueError, match=r"not on a uniform grid: the step from sample 899 to 900.*resample"):
        pl_lssvm(reg.Z, reg.y, THESIS_KERNEL, GAMMA, x=x)
    with pytest.raises(ValueError, match="must increase"):
        pl_lssvm(reg.Z, reg.y, THESIS_KERNEL, GAMMA, x=s.x[::-1])
    x = s.x.copy()
    x[3] = np.nan
    with pytest.raises(ValueError, match="x has 1 non-finite.*sample 3"):
        pl_lssvm(reg.Z, reg.y, THESIS_KERNEL, GAMMA, x=x)
    y = reg.y.copy()
    y[44] = np.inf
    with pytest.raises(ValueError, match="y has 1 non-finite.*sample 44"):
        pl_lssvm(reg.Z, y, THESIS_KERNEL, GAMMA, Ts=s.Ts)
    with pytest.raises(ValueError, match="too few samples: 12.*at least 15"):
        pl_lssvm(reg.Z[:12], reg.y[:12], THESIS_KERNEL, GAMMA, Ts=s.Ts)
    with pytest.raises(ValueError, match="give x"):
        pl_lssvm(reg.Z, reg.y, THESIS_KERNEL, GAMMA)
    with pytest.raises(ValueError, match="gamma"):
        pl_lssvm(reg.Z, reg.y, THESIS_KERNEL, 0.0, Ts=s.Ts)
    xv = np.column_stack([s.x, reg.Z[:, 1]])
    kernel = Product(LocallyPeriodic(0.59, 0.42, 1 / 55, dims=0), SquaredExponential(0.05, dims=1))
    with pytest.raises(ValueError, match=r"exceeds dense_limit = 500.*time kernel on a uniform grid.*fewer samples"):
        pl_lssvm(reg.Z, reg.y, kernel, GAMMA, x=xv, dense_limit=500)
    with pytest.raises(ValueError, match="reads vector inputs"):
        pl_lssvm(reg.Z, reg.y, kernel, GAMMA, Ts=s.Ts)


def test_no_reversal_error_names_coulomb_column():
    s = simulate(1600, seed=3, reversals=False)
    reg = s.regression()
    with pytest.raises(ParameterError, match=r"'-sigma_n'.*No speed reversal.*\(coulomb=False\)") as err:
        pl_lssvm(reg.Z, reg.y, THESIS_KERNEL, GAMMA, Ts=s.Ts, names=reg.names)
    assert err.value.parameters == ("coulomb",) and "--" not in str(err.value)
    s2 = simulate(1600, seed=3, reversals=False, coulomb=False)
    reg2 = s2.regression()
    res = pl_lssvm(reg2.Z, reg2.y, THESIS_KERNEL, GAMMA, Ts=s2.Ts)
    np.testing.assert_allclose(res.beta, s2.beta, rtol=5e-3)
