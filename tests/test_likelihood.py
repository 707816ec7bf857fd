"""kernels.likelihood: REML likelihood (Toeplitz/Levinson vs dense) and hyperparameter tuning."""

import numpy as np
import pytest
from scipy.linalg import block_diag

from kernels.covariance import LocallyPeriodic, Product, SquaredExponential
from kernels.likelihood import log_marginal_likelihood, reml_terms, tune
from kernels.pl_lssvm import pl_lssvm

try:
    from tests.streams import shaker_stream
except ImportError:
    from streams import shaker_stream

THESIS = (0.59, 0.42, 50.3)
PSI = 1 / 55


def dense_reml(Z, y, A, intercept=True):
    """Reference REML (b integrated out, s² profiled) with numpy slogdet and dense solves."""
    n = y.size
    Zt = np.column_stack([np.ones(n), Z]) if intercept else Z
    p = Zt.shape[1]
    Ai_Z = np.linalg.solve(A, Zt)
    Ai_y = np.linalg.solve(A, y)
    M = Zt.T @ Ai_Z
    b = np.linalg.solve(M, Zt.T @ Ai_y)
    r = y - Zt @ b
    q = r @ np.linalg.solve(A, r)
    s2 = q / (n - p)
    return -0.5 * ((n - p) * (np.log(2 * np.pi * s2) + 1) + np.linalg.slogdet(A)[1]
                   + np.linalg.slogdet(M)[1] - np.linalg.slogdet(Zt.T @ Zt)[1])


@pytest.mark.parametrize("form", ["velocity-loop", "force-input"])
def test_toeplitz_likelihood_equals_dense(form):
    s = shaker_stream(501, amplitude=10.0, seed=11, form=form)
    reg = s.regression()
    kernel = LocallyPeriodic(*THESIS[:2], PSI)
    A = kernel(s.x) + np.eye(500) / THESIS[2]
    ref = dense_reml(reg.Z, reg.y, A, intercept=(form == "velocity-loop"))
    fast = log_marginal_likelihood(reg.Z, reg.y, kernel, THESIS[2], s.Ts, dense_limit=0)  # Levinson + PCG
    dense = log_marginal_likelihood(reg.Z, reg.y, kernel, THESIS[2], s.Ts)  # Cholesky path
    assert fast == pytest.approx(ref, rel=1e-8)
    assert dense == pytest.approx(ref, rel=1e-8)
    terms = reml_terms(reg.Z, reg.y, kernel, THESIS[2], s.Ts, dense_limit=0)
    assert terms.logdet_A == pytest.approx(np.linalg.slogdet(A)[1], rel=1e-10)
    assert terms.solver.startswith("pcg-")


def test_likelihood_invariant_to_column_scaling():
    s = shaker_stream(400, amplitude=10.0, seed=12)
    reg = s.regression()
    kernel = LocallyPeriodic(*THESIS[:2], PSI)
    a = log_marginal_likelihood(reg.Z, reg.y, kernel, 50.0, s.Ts)
    b = log_marginal_likelihood(reg.Z * [1.0, 1e3, 1e-2, 5.0], reg.y, kernel, 50.0, s.Ts)
    assert a == pytest.approx(b, rel=1e-10)


def test_segmented_likelihood_is_block_diagonal_reml():
    s = shaker_stream(601, amplitude=10.0, seed=13)
    reg = s.regression()
    kernel = LocallyPeriodic(0.3, 0.5, PSI)
    gamma = 80.0
    seg = log_marginal_likelihood(reg.Z, reg.y, kernel, gamma, s.Ts, segment=210)  # 3 segments of 200
    block = kernel(np.arange(200) * s.Ts) + np.eye(200) / gamma
    ref = dense_reml(reg.Z, reg.y, block_diag(block, block, block))
    assert seg == pytest.approx(ref, rel=1e-9)
    whole = log_marginal_likelihood(reg.Z, reg.y, kernel, gamma, s.Ts)
    assert log_marginal_likelihood(reg.Z, reg.y, kernel, gamma, s.Ts, segment=600) == pytest.approx(whole, rel=1e-12)


def test_tune_beats_thesis_values_and_recovers_beta():
    s = shaker_stream(1501, amplitude=10.0, seed=5, sweep=True)
    reg = s.regression()
    seen = []
    res = tune(reg.Z, reg.y, s.Ts, PSI, max_evaluations=120, progress=lambda *a: seen.append(a))
    assert res.evaluations == len(seen) > 28
    assert res.period == PSI
    thesis_kernel = LocallyPeriodic(*THESIS[:2], PSI)
    ll_thesis = log_marginal_likelihood(reg.Z, reg.y, thesis_kernel, THESIS[2], s.Ts)
    ll_tuned = log_marginal_likelihood(reg.Z, reg.y, res.kernel(), res.gamma, s.Ts)
    assert ll_tuned > ll_thesis
    pl = pl_lssvm(reg.Z, reg.y, res.kernel(), res.gamma, Ts=s.Ts)
    err = np.abs(pl.beta[:2] - s.beta[:2]) / s.beta[:2]
    assert np.all(err < 0.005), err


def test_errors():
    s = shaker_stream(1000, amplitude=10.0, seed=1)
    reg = s.regression()
    vector = Product(LocallyPeriodic(0.5, 0.4, PSI, dims=0), SquaredExponential(1.0, dims=1))
    with pytest.raises(ValueError, match="not a time kernel"):
        log_marginal_likelihood(reg.Z, reg.y, vector, 50.0, s.Ts, names=reg.names)
    with pytest.raises(ValueError, match="Ts"):
        log_marginal_likelihood(reg.Z, reg.y, LocallyPeriodic(0.5, 0.4, PSI), 50.0, 0.0)
    with pytest.raises(ValueError, match="bounds"):
        tune(reg.Z, reg.y, s.Ts, PSI, bounds=((1, 0.5), (0.1, 1), (1, 10)))
    with pytest.raises(ValueError, match="period"):
        tune(reg.Z, reg.y, s.Ts, -1.0)
