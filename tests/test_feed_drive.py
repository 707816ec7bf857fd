"""kernels.feed_drive: β ↔ physical round trips, regressors, free run, force conversion (method §1–2, §6)."""

import numpy as np
import pytest

from kernels.feed_drive import (
    beta_names,
    beta_to_physical,
    check_validity,
    coulomb_indicators,
    disturbance_to_force,
    force_to_disturbance,
    friction_transform,
    physical_covariance,
    physical_to_beta,
    regressors,
    rest_samples,
    simulate_free_run,
    validity_problems,
)
from replay.streams import GAIN, TS, shaker_stream, simulate

PHYS = dict(inertia=120.0, damping=85.0, coulomb_pos=18.0, coulomb_neg=23.0)


@pytest.mark.parametrize("coulomb", [True, False])
def test_velocity_loop_round_trip_with_gain(coulomb):
    beta = physical_to_beta("velocity-loop", TS, gain=GAIN, coulomb=coulomb, **PHYS)
    assert beta.shape == (4 if coulomb else 2,)
    phys = beta_to_physical("velocity-loop", beta, TS, gain=GAIN, coulomb=coulomb)
    assert phys.inertia == pytest.approx(PHYS["inertia"], rel=1e-10)
    assert phys.damping == pytest.approx(PHYS["damping"], rel=1e-10)
    if coulomb:
        assert phys.coulomb_pos == pytest.approx(PHYS["coulomb_pos"], rel=1e-10)
        assert phys.coulomb_neg == pytest.approx(PHYS["coulomb_neg"], rel=1e-10)
    else:
        assert phys.coulomb_pos is None and phys.coulomb_neg is None
    again = physical_to_beta("velocity-loop", TS, phys.inertia, phys.damping, gain=GAIN, coulomb=coulomb,
                             coulomb_pos=phys.coulomb_pos or 0.0, coulomb_neg=phys.coulomb_neg or 0.0)
    np.testing.assert_allclose(again, beta, rtol=1e-12)


@pytest.mark.parametrize("coulomb", [True, False])
def test_velocity_loop_without_gain_gives_ratios(coulomb):
    beta = physical_to_beta("velocity-loop", TS, gain=GAIN, coulomb=coulomb, **PHYS)
    phys = beta_to_physical("velocity-loop", beta, TS, coulomb=coulomb)
    assert phys.inertia is None and phys.damping is None and phys.gain is None
    assert phys.inertia_over_gain == pytest.approx(PHYS["inertia"] / GAIN, rel=1e-10)
    assert phys.damping_over_gain == pytest.approx(PHYS["damping"] / GAIN, rel=1e-10)
    if coulomb:
        assert phys.coulomb_pos_over_gain == pytest.approx(PHYS["coulomb_pos"] / GAIN, rel=1e-10)
        assert phys.coulomb_neg_over_gain == pytest.approx(PHYS["coulomb_neg"] / GAIN, rel=1e-10)
    assert "inertia" not in phys.to_dict()


@pytest.mark.parametrize("coulomb", [True, False])
def test_force_input_round_trip(coulomb):
    beta = physical_to_beta("force-input", TS, offset=3.5, coulomb=coulomb, **PHYS)
    assert beta.shape == (5 if coulomb else 3,)
    phys = beta_to_physical("force-input", beta, TS, coulomb=coulomb)
    assert phys.inertia == pytest.approx(PHYS["inertia"], rel=1e-10)
    assert phys.damping == pytest.approx(PHYS["damping"], rel=1e-10)
    assert phys.offset == pytest.approx(3.5, rel=1e-10)
    if coulomb:
        assert phys.coulomb_pos == pytest.approx(PHYS["coulomb_pos"], rel=1e-10)
        assert phys.coulomb_neg == pytest.approx(PHYS["coulomb_neg"], rel=1e-10)


def test_thesis_case1_beta():
    beta = physical_to_beta("velocity-loop", TS, 100.0, 100.0, gain=GAIN)
    assert beta[0] == pytest.approx(0.834, rel=1e-12)
    assert beta[1] == pytest.approx(0.163, abs=1e-3)


def test_beta_to_physical_rejects_unstable():
    with pytest.raises(ValueError, match="0 < p_d < 1"):
        beta_to_physical("velocity-loop", [0.5, 0.6, 0.0, 0.0], TS, gain=GAIN)
    with pytest.raises(ValueError, match="entries"):
        beta_to_physical("force-input", [0.5, 0.6], TS)
    with pytest.raises(ValueError, match="loop gain"):
        physical_to_beta("velocity-loop", TS, 1.0, 1.0)
    with pytest.raises(ValueError, match="not known"):
        physical_to_beta("torque", TS, 1.0, 1.0)


@pytest.mark.parametrize("form,coulomb,m", [("velocity-loop", True, 4), ("velocity-loop", False, 2),
                                            ("force-input", True, 5), ("force-input", False, 3)])
def test_regressors_shapes_and_names(form, coulomb, m):
    n = 50
    v = np.linspace(-0.1, 0.1, n)
    kw = {"v_ref": v * 1.1} if form == "velocity-loop" else {"u": v * 300.0}
    reg = regressors(form, v, omega=0.01, coulomb=coulomb, **kw)
    assert reg.Z.shape == (n - 1, m)
    assert reg.y.shape == (n - 1,)
    assert reg.names == beta_names(form, coulomb)
    np.testing.assert_array_equal(reg.y, v[1:])
    np.testing.assert_array_equal(reg.Z[:, 1], v[:-1])
    if coulomb:
        np.testing.assert_array_equal(reg.Z[:, 2], -(v[:-1] > 0.01).astype(float))
        np.testing.assert_array_equal(reg.Z[:, 3], -(v[:-1] < -0.01).astype(float))
    if form == "force-input":
        np.testing.assert_array_equal(reg.Z[:, -1], 1.0)
        assert reg.names[-1] == "one"


def test_regressors_errors():
    v = np.zeros(20)
    with pytest.raises(ValueError, match="v_ref has 19 samples but v_meas has 20"):
        regressors("velocity-loop", v, v_ref=np.zeros(19))
    bad = v.copy()
    bad[7] = np.nan
    with pytest.raises(ValueError, match="v_ref has 1 non-finite value.*sample 7"):
        regressors("velocity-loop", v, v_ref=bad)
    with pytest.raises(ValueError, match="v_meas has 1 non-finite value.*sample 7"):
        regressors("velocity-loop", bad, v_ref=v)
    with pytest.raises(ValueError, match="u has 1 non-finite"):
        regressors("force-input", v, u=bad)
    with pytest.raises(ValueError, match="needs v_ref"):
        regressors("velocity-loop", v)
    with pytest.raises(ValueError, match="needs u"):
        regressors("force-input", v, v_ref=v)
    with pytest.raises(ValueError, match="dead band"):
        regressors("velocity-loop", v, v_ref=v, omega=-1.0)


@pytest.mark.parametrize("form", ["velocity-loop", "force-input"])
def test_free_run_equals_generating_recursion(form):
    kw = {"offset": 2.0} if form == "force-input" else {}
    s = shaker_stream(1500, amplitude=10.0, noise=0.0, seed=3, form=form, **kw)
    v_hat = simulate_free_run(form, s.beta, s.v_meas[0], s.exogenous, omega=s.omega, coulomb=True,
                              disturbance=np.append(s.f, 0.0))
    np.testing.assert_allclose(v_hat, s.v_meas, rtol=1e-10, atol=1e-14)


def test_free_run_without_disturbance_matches_noise_free_stream():
    s = simulate(800, noise=0.0, seed=5, coulomb=False)
    v_hat = simulate_free_run("velocity-loop", s.beta, 0.0, s.exogenous, coulomb=False)
    np.testing.assert_allclose(v_hat, s.v_meas, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("form,gain", [("velocity-loop", GAIN), ("force-input", None)])
def test_force_disturbance_inverse(form, gain):
    beta = physical_to_beta(form, TS, gain=gain, **PHYS)
    force = np.random.default_rng(0).normal(0, 30.0, 200)
    f = force_to_disturbance(form, beta, force, gain=gain)
    np.testing.assert_allclose(disturbance_to_force(form, beta, f, gain=gain), force, rtol=1e-12)
    b = (1 - np.exp(-PHYS["damping"] * TS / PHYS["inertia"])) / PHYS["damping"]
    np.testing.assert_allclose(f, -b * force, rtol=1e-10)


def test_velocity_loop_force_needs_gain():
    beta = physical_to_beta("velocity-loop", TS, gain=GAIN, **PHYS)
    with pytest.raises(ValueError, match="loop gain"):
        disturbance_to_force("velocity-loop", beta, np.zeros(3))


@pytest.mark.parametrize("form,gain", [("velocity-loop", GAIN), ("force-input", None)])
def test_intercept_round_trip_in_both_forms(form, gain):
    beta = physical_to_beta(form, TS, gain=gain, offset=-3.0, intercept=True, **PHYS)
    names = beta_names(form, True, intercept=True)
    assert names[-1] == "one" and beta.size == len(names)
    phys = beta_to_physical(form, beta, TS, gain=gain, names=names)
    assert phys.offset == pytest.approx(-3.0, rel=1e-10)
    assert phys.coulomb == pytest.approx(0.5 * (PHYS["coulomb_pos"] + PHYS["coulomb_neg"]), rel=1e-10)
    assert set(phys.to_dict()) == {"inertia", "damping", "coulomb", "coulomb_pos", "coulomb_neg", "offset"}
    if form == "velocity-loop":
        ratios = beta_to_physical(form, beta, TS, names=names).to_dict()  # K unknown: only /K forms
        assert set(ratios) == {f"{k}_over_gain" for k in phys.to_dict()}
        assert ratios["offset_over_gain"] == pytest.approx(-3.0 / GAIN, rel=1e-10)


@pytest.mark.parametrize("rest", [True, False])
def test_friction_transform_is_a_reparametrisation(rest):
    """Z_id = Z T spans −τ (and −|τ| with rest) instead of −σ_p, −σ_n; β = T θ maps back."""
    names = beta_names("force-input", True)
    T, id_names = friction_transform(names, rest)
    assert id_names == ("u", "v_meas", "-tau") + (("-abs_tau",) if rest else ()) + ("one",)
    v = np.array([0.5, -0.5, 0.0, 0.2])
    sp, sn = coulomb_indicators(v, 0.1)
    Z = np.column_stack([np.ones(4), v, -sp, -sn, np.ones(4)])
    Zid = Z @ T
    tau = sp - sn
    np.testing.assert_array_equal(Zid[:, 2], -tau)
    if rest:
        np.testing.assert_array_equal(Zid[:, 3], -np.abs(tau))
    # Fc = 20 N symmetric, asymmetry a = −2 N (coulomb_pos 18, coulomb_neg 22), b = 1e-4
    b = 1e-4
    theta = np.array([b, 0.99, b * 20.0] + ([b * -2.0] if rest else []) + [b * 3.0])
    beta = T @ theta
    phys = beta_to_physical("force-input", beta, TS)
    assert phys.coulomb == pytest.approx(20.0)
    assert phys.coulomb_pos == pytest.approx(18.0 if rest else 20.0)
    assert phys.coulomb_neg == pytest.approx(22.0 if rest else 20.0)
    assert phys.offset == pytest.approx(-3.0)


def test_rest_is_a_long_stay_in_the_dead_band_not_a_reversal():
    v = np.concatenate([np.full(50, 0.1), np.linspace(0.1, -0.1, 5), np.full(50, -0.1)])  # 1 sample near 0
    assert rest_samples(v, 0.01, 0.003) == 0
    v = np.concatenate([np.full(50, 0.1), np.zeros(40), np.full(50, -0.1)])  # 40 samples = 0.12 s at rest
    assert rest_samples(v, 0.01, 0.003) == 40


def test_delta_method_matches_monte_carlo():
    beta = physical_to_beta("force-input", TS, 95.0, 200.0, coulomb_pos=20.0, coulomb_neg=20.0, offset=-3.0)
    rng = np.random.default_rng(0)
    G = rng.normal(size=(5, 5))
    cov = (G @ G.T) * (1e-4 * np.abs(beta))[:, None] * (1e-4 * np.abs(beta))[None, :]
    phys, se = physical_covariance("force-input", beta, cov, TS)
    draws = rng.multivariate_normal(beta, cov, size=4000)
    mc = np.array([[beta_to_physical("force-input", d, TS).to_dict()[k] for k in phys] for d in draws])
    np.testing.assert_allclose([se[k] for k in phys], mc.std(axis=0), rtol=0.08)


def test_validity_problems_name_the_cause_and_what_to_try():
    good = physical_to_beta("velocity-loop", TS, 100.0, 100.0, gain=GAIN, coulomb_pos=5.0, coulomb_neg=5.0)
    assert validity_problems("velocity-loop", good, TS, gain=GAIN) == []
    unstable = good.copy()
    unstable[1] += 0.01  # p_d = β1 + β2 > 1
    (msg,) = validity_problems("velocity-loop", unstable, TS, gain=GAIN)
    assert "pole" in msg and "≥ 1" in msg and "--period" in msg and "--method ls" in msg
    negative_gain = good.copy()
    negative_gain[0] = -negative_gain[0]
    assert any("input gain" in m and "sign of the command" in m
               for m in validity_problems("velocity-loop", negative_gain, TS, gain=GAIN))
    negative = physical_to_beta("velocity-loop", TS, 100.0, 100.0, gain=GAIN, coulomb_pos=-5.0, coulomb_neg=-5.0)
    (msg,) = validity_problems("velocity-loop", negative, TS, gain=GAIN)
    assert "Coulomb friction negative beyond its uncertainty" in msg
    # within its uncertainty a slightly negative friction is not a fault
    assert validity_problems("velocity-loop", negative, TS, gain=GAIN,
                             physical_se={"coulomb": 4.0, "coulomb_pos": 4.0, "coulomb_neg": 4.0}) == []
    with pytest.raises(ValueError, match="cannot be right.*pole"):
        check_validity("velocity-loop", unstable, TS, gain=GAIN)
