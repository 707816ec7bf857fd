"""kernels.least_squares: QR least squares (method §3) and the shared input validation."""

import numpy as np
import pytest

from kernels.least_squares import least_squares, validate_regression
from replay.streams import shaker_stream, simulate


@pytest.mark.parametrize("form", ["velocity-loop", "force-input"])
def test_noise_free_stream_recovers_beta(form):
    kw = {"offset": 1.5} if form == "force-input" else {}
    s = simulate(2000, form=form, noise=0.0, seed=2, **kw)
    reg = s.regression()
    res = least_squares(reg.Z, reg.y, reg.names)
    np.testing.assert_allclose(res.beta, s.beta, rtol=1e-9)
    assert res.rmse < 1e-12
    assert res.names == reg.names


def test_stderr_matches_dense_formula_and_residuals():
    s = simulate(3000, noise=2e-5, seed=4)
    reg = s.regression()
    res = least_squares(reg.Z, reg.y)
    Z, y = reg.Z, reg.y
    beta_ref = np.linalg.solve(Z.T @ Z, Z.T @ y)
    np.testing.assert_allclose(res.beta, beta_ref, rtol=1e-7)
    np.testing.assert_allclose(res.residuals, y - Z @ res.beta, rtol=0, atol=1e-15)
    sigma2 = np.sum(res.residuals ** 2) / (Z.shape[0] - Z.shape[1])
    assert res.sigma2 == pytest.approx(sigma2, rel=1e-12)
    cov_ref = sigma2 * np.linalg.inv(Z.T @ Z)
    np.testing.assert_allclose(res.cov, cov_ref, rtol=1e-8)
    np.testing.assert_allclose(res.stderr, np.sqrt(np.diag(cov_ref)), rtol=1e-8)
    assert res.rmse == pytest.approx(np.sqrt(np.mean(res.residuals ** 2)), rel=1e-12)
    assert res.dof == Z.shape[0] - 4
    # the truth is within a few standard errors (white equation noise: LS unbiased)
    assert np.all(np.abs(res.beta - s.beta) < 5 * res.stderr)


def test_stderr_agrees_with_monte_carlo_spread():
    betas, errs = [], []
    for seed in range(30):
        s = simulate(1200, noise=5e-5, seed=100 + seed, coulomb=False)
        reg = s.regression()
        r = least_squares(reg.Z, reg.y)
        betas.append(r.beta)
        errs.append(r.stderr)
    spread = np.std(betas, axis=0, ddof=1)
    ratio = spread / np.mean(errs, axis=0)
    assert np.all((ratio > 0.6) & (ratio < 1.6)), ratio


def test_ls_is_biased_by_periodic_disturbance():
    s = shaker_stream(2500, amplitude=10.0, seed=1)
    reg = s.regression()
    res = least_squares(reg.Z, reg.y)
    rel = np.abs(res.beta[:2] - s.beta[:2]) / np.abs(s.beta[:2])
    assert rel[1] > 0.02  # β2 biased by more than 2 % (PL-LSSVM: < 0.5 %, test_pl_lssvm)


def test_errors_name_the_problem():
    s = simulate(200, seed=1)
    reg = s.regression()
    Z = reg.Z.copy()
    Z[17, 1] = np.inf
    with pytest.raises(ValueError, match=r"Z column 1 \('v_meas'\).*sample 17"):
        least_squares(Z, reg.y, reg.names)
    y = reg.y.copy()
    y[5] = np.nan
    with pytest.raises(ValueError, match="y has 1 non-finite.*sample 5"):
        least_squares(reg.Z, y, reg.names)
    with pytest.raises(ValueError, match="too few samples: 12.*at least 14"):
        least_squares(reg.Z[:12], reg.y[:12], reg.names)
    with pytest.raises(ValueError, match="must align"):
        least_squares(reg.Z, reg.y[:-1])
    with pytest.raises(ValueError, match="names has 2"):
        least_squares(reg.Z, reg.y, names=("a", "b"))


def test_no_reversal_names_coulomb_column():
    s = simulate(1500, seed=3, reversals=False)
    reg = s.regression()
    with pytest.raises(ValueError, match=r"'-sigma_n'.*no motion below −Ω.*coulomb=False"):
        least_squares(reg.Z, reg.y, reg.names)


def test_collinear_columns_are_named():
    s = simulate(500, seed=3)
    reg = s.regression()
    Z = np.column_stack([reg.Z, 2.0 * reg.Z[:, 0]])
    with pytest.raises(ValueError, match=r"linearly dependent.*'v_ref'.*'copy'"):
        least_squares(Z, reg.y, reg.names + ("copy",))


def test_no_dead_band_samples_with_intercept():
    s = simulate(600, seed=3)
    reg = s.regression()
    Z = reg.Z.copy()
    Z[:, 2] = -(reg.Z[:, 1] >= 0).astype(float)
    Z[:, 3] = -(reg.Z[:, 1] < 0).astype(float)
    with pytest.raises(ValueError, match="outside the dead band"):
        validate_regression(Z, reg.y, reg.names, intercept=True)
