"""kernels.likelihood: REML likelihood (Toeplitz/Levinson vs dense) and hyperparameter tuning."""

import numpy as np
import pytest
from reml_reference import dense_gls_cov, dense_reml

from kernels.covariance import LocallyPeriodic, Product, SquaredExponential
from kernels.levinson import levinson_whiten
from kernels.likelihood import default_bounds, log_evidence, log_marginal_likelihood, reml_terms, tune
from kernels.pl_lssvm import pl_lssvm
from replay.streams import shaker_stream

THESIS = (0.59, 0.42, 50.3)
PSI = 1 / 55


@pytest.mark.parametrize("form", ["velocity-loop", "force-input"])
def test_levinson_likelihood_and_gls_covariance_equal_dense(form):
    s = shaker_stream(501, amplitude=10.0, seed=11, form=form)
    reg = s.regression()
    kernel = LocallyPeriodic(*THESIS[:2], PSI)
    A = kernel(s.x) + np.eye(500) / THESIS[2]
    intercept = form == "velocity-loop"
    ref = dense_reml(reg.Z, reg.y, A, intercept=intercept)
    terms = reml_terms(reg.Z, reg.y, kernel, THESIS[2], s.Ts)
    assert terms.solver == "levinson"
    assert terms.log_likelihood == pytest.approx(ref, rel=1e-9)
    assert terms.logdet_A == pytest.approx(np.linalg.slogdet(A)[1], rel=1e-10)
    np.testing.assert_allclose(terms.cov, dense_gls_cov(reg.Z, reg.y, A, intercept), rtol=1e-7)
    assert terms.intercept == intercept and terms.beta.size == reg.Z.shape[1]
    # least squares is the same reading with A = I (comparable REML)
    ls = reml_terms(reg.Z, reg.y, None, None, s.Ts)
    assert ls.log_likelihood == pytest.approx(dense_reml(reg.Z, reg.y, np.eye(500), intercept=intercept), rel=1e-10)
    np.testing.assert_allclose(ls.cov, dense_gls_cov(reg.Z, reg.y, np.eye(500), intercept), rtol=1e-8)


def test_log_evidence_penalises_fitted_hyperparameters():
    assert log_evidence(100.0, 0, 1010, 10) == 100.0
    assert log_evidence(100.0, 3, 1010, 10) == pytest.approx(100.0 - 1.5 * np.log(1000.0))


def test_likelihood_invariant_to_column_scaling():
    s = shaker_stream(400, amplitude=10.0, seed=12)
    reg = s.regression()
    kernel = LocallyPeriodic(*THESIS[:2], PSI)
    a = log_marginal_likelihood(reg.Z, reg.y, kernel, 50.0, s.Ts)
    b = log_marginal_likelihood(reg.Z * [1.0, 1e3, 1e-2, 5.0], reg.y, kernel, 50.0, s.Ts)
    assert a == pytest.approx(b, rel=1e-10)


def test_order_m_likelihood_and_gls_equal_the_dense_reml_of_its_covariance():
    """The order-m REML (kernels.levinson, eq. V2) is the exact REML and GLS of the covariance Ã = L̃L̃ᵀ it
    implies (a valid Gaussian process), and near the exact one when m covers the kernel's memory."""
    s = shaker_stream(701, amplitude=10.0, seed=13)
    reg = s.regression()
    kernel = LocallyPeriodic(0.3, 0.5, PSI)
    gamma, m = 80.0, 250
    approx = reml_terms(reg.Z, reg.y, kernel, gamma, s.Ts, max_order=m)
    assert approx.order == m and approx.solver == f"levinson-ar{m}"
    column = kernel.lag(np.arange(700) * s.Ts)
    column[0] += 1 / gamma
    L_inv = levinson_whiten(column, np.eye(700), max_order=m).white
    A_tilde = np.linalg.inv(L_inv.T @ L_inv)
    assert approx.log_likelihood == pytest.approx(dense_reml(reg.Z, reg.y, A_tilde), rel=1e-9)
    np.testing.assert_allclose(approx.cov, dense_gls_cov(reg.Z, reg.y, A_tilde), rtol=1e-6)
    exact = reml_terms(reg.Z, reg.y, kernel, gamma, s.Ts)
    assert exact.order == 699 and abs(approx.log_likelihood - exact.log_likelihood) < 5.0
    adaptive = reml_terms(reg.Z, reg.y, kernel, gamma, s.Ts, tol=0.5)
    assert adaptive.log_likelihood == pytest.approx(exact.log_likelihood, abs=2.0)


def test_tune_beats_thesis_values_and_recovers_beta():
    s = shaker_stream(1501, amplitude=10.0, seed=5, sweep=True)
    reg = s.regression()
    seen = []
    res = tune(reg.Z, reg.y, s.Ts, PSI, max_evaluations=60, progress=lambda *a: seen.append(a))
    assert res.evaluations == len(seen) > 10
    assert res.period == PSI and res.kind == "locally_periodic"
    thesis_kernel = LocallyPeriodic(*THESIS[:2], PSI)
    ll_thesis = log_marginal_likelihood(reg.Z, reg.y, thesis_kernel, THESIS[2], s.Ts)
    ll_tuned = log_marginal_likelihood(reg.Z, reg.y, res.kernel(), res.gamma, s.Ts)
    assert ll_tuned > ll_thesis
    assert res.log_likelihood == pytest.approx(ll_tuned, rel=1e-12)  # the exact objective
    assert res.terms.log_likelihood == pytest.approx(ll_tuned, rel=1e-12)
    pl = pl_lssvm(reg.Z, reg.y, res.kernel(), res.gamma, Ts=s.Ts)
    err = np.abs(pl.beta[:2] - s.beta[:2]) / s.beta[:2]
    assert np.all(err < 0.005), err


def test_default_bounds_scale_with_the_record_and_bounds_are_reported():
    b = default_bounds("locally_periodic", 3000, 0.001, 0.2)
    assert b["sigma1"] == (0.4, 3.0) and b["sigma2"][0] == pytest.approx(0.05) and b["gamma"] == (1e-2, 1e6)
    assert default_bounds("locally_periodic", 3000, 0.001, 0.002)["sigma2"][0] == pytest.approx(np.pi / 4)
    assert default_bounds("squared_exponential", 3000, 0.001)["lengthscale"] == (0.01, 3.0)
    # white noise only: nothing for a kernel to explain, γ ends on its lower bound and is reported
    rng = np.random.default_rng(4)
    n = 800
    Z = np.column_stack([np.ones(n), rng.normal(size=n)])
    y = Z @ [0.5, 2.0] + rng.normal(size=n)
    res = tune(Z, y, 0.01, kind="squared_exponential", max_evaluations=25)
    assert res.kind == "squared_exponential" and set(res.hyper) == {"lengthscale"}
    assert res.on_bound  # a white residual leaves the kernel nothing to do: it ends on a bound
    ls = log_marginal_likelihood(Z, y, None, None, 0.01)
    assert res.log_likelihood - ls < 3.0  # and adds (next to) nothing to the evidence


def test_errors():
    s = shaker_stream(1000, amplitude=10.0, seed=1)
    reg = s.regression()
    vector = Product(LocallyPeriodic(0.5, 0.4, PSI, dims=0), SquaredExponential(1.0, dims=1))
    with pytest.raises(ValueError, match="not a time kernel"):
        log_marginal_likelihood(reg.Z, reg.y, vector, 50.0, s.Ts, names=reg.names)
    with pytest.raises(ValueError, match="Ts"):
        log_marginal_likelihood(reg.Z, reg.y, LocallyPeriodic(0.5, 0.4, PSI), 50.0, 0.0)
    with pytest.raises(ValueError, match="bounds"):
        tune(reg.Z, reg.y, s.Ts, PSI, bounds={"sigma1": (1, 0.5), "sigma2": (0.1, 1), "gamma": (1, 10)})
    with pytest.raises(ValueError, match="bounds must give"):
        tune(reg.Z, reg.y, s.Ts, PSI, bounds={"sigma1": (1, 2)})
    with pytest.raises(ValueError, match="kernel family"):
        tune(reg.Z, reg.y, s.Ts, PSI, kind="matern")
    with pytest.raises(ValueError, match="period"):
        tune(reg.Z, reg.y, s.Ts, -1.0)
