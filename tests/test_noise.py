"""kernels.noise: the measurement noise in a window of residuals, not inflated by a disturbance."""

import numpy as np
import pytest

from feedio.mcapio import read_trial
from kernels.errors import ParameterError
from kernels.feed_drive import regressors
from kernels.noise import white_noise


def _ma1(n, pole, sigma, seed):
    e = np.random.default_rng(seed).normal(0.0, sigma, n + 1)
    return e[1:] - pole * e[:-1]  # eq. N1: ε(k) = n(k+1) − p n(k)


@pytest.mark.parametrize("pole", [0.0, 0.99])
@pytest.mark.parametrize("n", [700, 13320])
def test_unbiased_on_its_own_noise_with_the_spread_it_reports(n, pole):
    vals = np.array([white_noise(_ma1(n, pole, 2e-6, seed), pole=pole).sigma_n for seed in range(24)])
    assert abs(vals.mean() / 2e-6 - 1.0) < 0.02
    est = white_noise(_ma1(n, pole, 2e-6, 99), pole=pole)
    assert est.sigma_eps == pytest.approx(est.sigma_n * np.sqrt(1 + pole * pole))
    # the reported standard error is of the size of the spread seen (within a factor of 2)
    spread = vals.std() * np.sqrt(1 + pole * pole)
    assert 0.5 < est.se_eps / spread < 2.0


def test_a_periodic_disturbance_a_step_and_glitches_do_not_inflate_it():
    """The issue's case: a periodic disturbance 200× the noise inflated the dead band's noise 200×. Here lines
    at 55 Hz and 110 Hz far above the noise, a force step and repeated samples leave it within 10 %."""
    n, Ts, pole, sigma = 13320, 1 / 333, 0.99, 5e-6
    t = np.arange(n) * Ts
    x = _ma1(n, pole, sigma, 3)
    x += 1e-3 * np.sin(2 * np.pi * 55 * t) + 3e-4 * np.sin(2 * np.pi * 110 * t + 1.0) + 2e-4 * (t > 20)
    x[np.random.default_rng(4).integers(0, n, 10)] += 1e-3
    est = white_noise(x, pole=pole)
    assert est.sigma_n == pytest.approx(sigma, rel=0.1)
    assert x.std() > 100 * sigma  # what a plain standard deviation would have said


@pytest.mark.parametrize("scenario, seed", [("shaker-constant", 2), ("milling-incdec", 2), ("shaker-sweep", 2)])
def test_on_simulated_trials_the_true_noise_through_the_true_model(simulated, scenario, seed):
    """The residual of the true β (what the monitor sees with a right model: disturbance + ε) gives the
    simulated v_meas noise (milling: +13 % from the recorder's repeated samples, which are noise too)."""
    trial = read_trial(simulated(scenario, seed=seed, duration=20.0))
    truth = trial.meta.truth
    reg = regressors(trial.meta.form, trial.v_meas, v_ref=trial.v_ref, omega=truth.omega, coulomb=truth.coulomb)
    beta = np.asarray(truth.beta)
    resid = reg.y - reg.Z @ beta
    est = white_noise(resid, pole=float(beta[0] + beta[1]))
    sigma = truth.scenario["noise"]["v_meas_std"]
    assert est.sigma_n == pytest.approx(sigma, rel=0.2), (est.sigma_n, sigma)
    window = white_noise(resid[:1665], pole=float(beta[0] + beta[1]))  # 5 s, as the monitor would run it
    assert window.sigma_n == pytest.approx(sigma, rel=0.35)


def test_bad_windows_are_refused_naming_the_parameter():
    with pytest.raises(ParameterError, match="at least 64") as exc:
        white_noise(np.zeros(10))
    assert exc.value.parameters == ("residual",)
    with pytest.raises(ParameterError, match="non-finite"):
        white_noise(np.r_[np.zeros(100), np.nan])
    with pytest.raises(ParameterError, match="pole") as exc:
        white_noise(np.ones(100), pole=1.5)
    assert exc.value.parameters == ("pole",)
    with pytest.raises(ParameterError, match="band"):
        white_noise(np.random.default_rng(0).normal(size=100), band=(0.5, 0.2))
    with pytest.raises(ParameterError, match="window"):
        white_noise(np.random.default_rng(0).normal(size=1000), window=8)
